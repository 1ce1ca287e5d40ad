"""The matching stage: which photo pairs are matched, chosen from the photos, and their matching (pycolmap).

Exhaustive matching grows with the square of the photos; above ``--exhaustive-max`` ``--matcher auto`` pairs each
photo with a bounded number of others: video frames with their next (sequential, with loop detection), photos with
GPS with their nearest (spatial), the rest with the most alike by a vocabulary tree (Nister & Stewenius, CVPR
2006; built from their own SIFT unless ``--vocab-tree``). Pairs are matched in blocks, and COLMAP skips those the
database holds, so a stopped stage resumes where it was.
"""

from __future__ import annotations

import json
import math
import os
import sys
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import pycolmap

from hico_plugin.errors import HicoError
from hico_plugin.process.ingest import PhotoInfo
from hico_plugin.process.stages import Report, write_json_atomic
from hico_plugin.storage import atomic_path

if TYPE_CHECKING:
    from hico_plugin.process.sfm import SfmOptions

MatcherName = Literal["exhaustive", "sequential", "spatial", "vocabtree"]
SEQUENTIAL_OVERLAP = 10
"""Frames after each frame that sequential pairing matches it with (COLMAP's default), besides those
2, 4, 8... frames on (quadratic overlap)."""
TREE_WORDS = 4096
"""Visual words of a vocabulary tree built from the photos: a vocabulary for one capture, learnt by
k-means from 39 descriptors a word (faiss's smallest sample per centroid), a fixed cost of minutes on
a CPU beside the hours of matching it saves. COLMAP's published trees (32K words for 1K-10K photos)
can be given with --vocab-tree instead."""
TREE_ITERATIONS = 10
"""k-means iterations of the tree's words: retrieval needs words that split the descriptors, not a
converged clustering."""
MATCH_BLOCKS = 50
"""The pairs are matched in about this many blocks: a progress step and a resume point each."""


def choose_matcher(infos: list[PhotoInfo], options: SfmOptions, ordered: bool) -> tuple[MatcherName, str]:
    """The matcher for photos ``infos`` (``ordered``: the frames of one video, in time order) and why,
    in words: ``options.matcher`` unless it is ``auto``; then every pair up to ``options.exhaustive_max``
    photos, else sequential for ordered frames, spatial when every photo carries a GPS position (more
    than half of them distinct: a position repeated throughout is a stale fix, not a place), else
    vocabulary-tree retrieval."""
    count = len(infos)
    if options.matcher != "auto":
        return options.matcher, f"asked for (--matcher {options.matcher})"
    if count <= options.exhaustive_max:
        return "exhaustive", f"{count} photos, at most --exhaustive-max {options.exhaustive_max}: every pair"
    bounded = f"over --exhaustive-max {options.exhaustive_max}, each matched with a bounded number of others"
    if ordered:
        return "sequential", (f"{count} video frames in order, {bounded}: its next {SEQUENTIAL_OVERLAP}, those 2, "
                              "4, 8... on, and the loop closures a vocabulary tree finds")
    located = [info.gps for info in infos if info.gps is not None]
    if len(located) == count and len(set(located)) > count // 2:
        return "spatial", f"{count} photos with GPS in their EXIF, {bounded}: the {options.neighbors} nearest"
    if not located:
        gps = "none with GPS in its EXIF"
    elif len(located) < count:
        gps = f"GPS in the EXIF of only {len(located)} (spatial matching needs every photo's)"
    else:
        gps = f"their GPS giving only {len(set(located))} distinct positions"
    return "vocabtree", f"{count} photos, {gps}, {bounded}: the {options.neighbors} most alike by a vocabulary tree"


def check_vocab_tree(options: SfmOptions) -> int:
    """The words of ``options.vocab_tree`` (a HicoError for a file pycolmap cannot read), checked
    before any feature is extracted; 0 when none is given (one is built from the photos)."""
    if options.vocab_tree is None:
        return 0
    path = options.vocab_tree.expanduser()
    try:
        return pycolmap.VisualIndex.read(path).num_visual_words()
    except Exception as err:  # noqa: BLE001  (pycolmap raises its own types for a bad file)
        raise HicoError(f"--vocab-tree {path}: not a vocabulary tree pycolmap reads ({err})") from None


def match(database: Path, matcher: MatcherName, options: SfmOptions, work: Path, key: str, report: Report,
          say: Callable[[str], None]) -> dict[str, Any]:
    """Match the pairs ``matcher`` chooses among the images of ``database`` (stage key ``key``: a
    stopped run's matches are kept for the same key, cleared for another); returns
    ``{"matcher", "pairs": candidate pairs, "verified": pairs with verified matches, "tree_words"}``."""
    resuming = _resume_or_clear(work / "matching.json", key, database)
    tree, words = None, 0
    if matcher in ("sequential", "vocabtree"):
        tree, words = _vocab_tree(database, work / "vocab_tree.bin", options, resuming, say)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = options.num_threads
    if matcher == "exhaustive":
        pairing = pycolmap.ExhaustivePairingOptions()
        generator, match_all = pycolmap.ExhaustivePairGenerator, pycolmap.match_exhaustive
    elif matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap, pairing.quadratic_overlap = SEQUENTIAL_OVERLAP, True
        pairing.loop_detection, pairing.vocab_tree_path = True, str(tree)
        pairing.loop_detection_num_images = options.neighbors
        generator, match_all = pycolmap.SequentialPairGenerator, pycolmap.match_sequential
    elif matcher == "spatial":
        pairing = pycolmap.SpatialPairingOptions()
        pairing.max_num_neighbors = options.neighbors
        generator, match_all = pycolmap.SpatialPairGenerator, pycolmap.match_spatial
    else:
        pairing = pycolmap.VocabTreePairingOptions()
        pairing.num_images, pairing.vocab_tree_path = options.neighbors, str(tree)
        generator, match_all = pycolmap.VocabTreePairGenerator, pycolmap.match_vocabtree
    if matcher != "exhaustive":  # exhaustive pairing is a plain loop, with no threads of its own
        pairing.num_threads = options.num_threads
    with pycolmap.Database.open(database) as db:
        if matcher == "spatial" and not any(prior.has_position() for prior in db.read_all_pose_priors()):
            raise HicoError("--matcher spatial: no photo has a GPS position COLMAP reads in its EXIF; use --matcher "
                            "auto, exhaustive, sequential or vocabtree")
        names = {image.image_id: image.name for image in db.read_all_images()}
        # COLMAP's pair lists split a line at spaces and skip lines starting with '#'
        listable = not any(name.startswith("#") or any(c.isspace() for c in name) for name in names.values())
        pairs = _unique(generator(pairing, db).all_pairs()) if listable else []
    if listable:
        _match_in_blocks(database, pairs, names, matching, work / "pairs.txt", report)
    else:  # one call, so no progress until it ends
        report(0, 1)
        match_all(database, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
        report(1, 1)
    with pycolmap.Database.open(database) as db:
        geometries = db.read_two_view_geometries()[1]
    verified = sum(len(geometry.inlier_matches) > 0 for geometry in geometries)
    return {"matcher": matcher, "pairs": len(pairs) if listable else len(geometries), "verified": verified,
            "tree_words": words}


def _resume_or_clear(state: Path, key: str, database: Path) -> bool:
    """Whether ``database``'s matches were made for stage key ``key`` (a stopped run of the same stage:
    kept); matches made with other options are cleared. ``state`` records the key being matched."""
    try:
        same = json.loads(state.read_text()).get("key") == key
    except (OSError, ValueError, AttributeError):
        same = False
    if not same:
        with pycolmap.Database.open(database) as db:
            db.clear_matches()
            db.clear_two_view_geometries()
        write_json_atomic(state, {"key": key})
    return same


def _unique(pairs: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """Each unordered pair once, in the order first met (pairing lists a pair from both of its ends)."""
    seen: dict[tuple[int, int], None] = {}
    for first, second in pairs:
        if first != second:
            seen.setdefault((min(first, second), max(first, second)), None)
    return list(seen)


def _match_in_blocks(database: Path, pairs: list[tuple[int, int]], names: dict[int, str],
                     matching: pycolmap.FeatureMatchingOptions, listing: Path, report: Report) -> None:
    block = max(1, math.ceil(len(pairs) / MATCH_BLOCKS))
    report(0, len(pairs))
    imported = pycolmap.ImportedPairingOptions()
    imported.match_list_path = str(listing)
    for start in range(0, len(pairs), block):
        chunk = pairs[start:start + block]
        listing.write_text("".join(f"{names[a]} {names[b]}\n" for a, b in chunk))
        pycolmap.match_image_pairs(database, matching_options=matching, pairing_options=imported,
                                   device=pycolmap.Device.cpu)
        report(start + len(chunk), len(pairs))
    listing.unlink(missing_ok=True)


def _vocab_tree(database: Path, path: Path, options: SfmOptions, reuse: bool,
                say: Callable[[str], None]) -> tuple[Path, int]:
    """``options.vocab_tree`` when given; else the tree at ``path`` when ``reuse`` (a stopped run of the
    same stage built it) or one built there from a sample of the database's SIFT descriptors, the same
    number from every photo, drawn with ``options.seed``. Returns (path, its words)."""
    if options.vocab_tree is not None:
        return options.vocab_tree.expanduser(), check_vocab_tree(options)
    if reuse and path.is_file():
        return path, pycolmap.VisualIndex.read(path).num_visual_words()
    rng = np.random.default_rng(options.seed)
    with pycolmap.Database.open(database) as db:
        images = db.read_all_images()
        per_photo = math.ceil(39 * TREE_WORDS / max(1, len(images)))
        samples = []
        for image in images:
            descriptors = db.read_descriptors(image.image_id).to_float().data
            keep = rng.choice(len(descriptors), min(per_photo, len(descriptors)), replace=False)
            samples.append(descriptors[np.sort(keep)])
    descriptors = np.concatenate(samples)
    words = min(TREE_WORDS, 2 ** int(np.log2(max(2, len(descriptors) // 39))))
    build = pycolmap.VisualIndex.BuildOptions()
    build.num_visual_words, build.num_iterations, build.num_rounds = words, TREE_ITERATIONS, 1
    build.num_threads = options.num_threads
    say(f"{'vocab tree':<12} {words:,} words from {len(descriptors):,} descriptors of {len(images)} photos")
    tree = pycolmap.VisualIndex.create(descriptors.shape[1], 64)  # SIFT's 128 dimensions, COLMAP's 64-bit embedding
    with _stderr_without("WARNING clustering"):
        tree.build(build, pycolmap.FeatureDescriptorsFloat(pycolmap.FeatureExtractorType.SIFT, descriptors))
    with atomic_path(path) as partial:
        tree.write(partial)
    return path, words


@contextmanager
def _stderr_without(prefix: str) -> Iterator[None]:
    """Hold back the lines starting with ``prefix`` that C code writes to stderr while the block runs
    (faiss's k-means warns that the tree's upper level has few points per centroid, which a tree of a
    few thousand words always has); the other lines are written once it ends."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as caught:
        os.dup2(caught.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            caught.seek(0)
            kept = [line for line in caught.read().decode(errors="replace").splitlines(keepends=True)
                    if not line.startswith(prefix)]
            sys.stderr.write("".join(kept))
