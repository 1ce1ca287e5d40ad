"""A plain triangle mesh (numpy arrays), cleaning it, and reading / writing it as PLY.

Kept independent of Open3D so that cleaning, sampling, metrics and file output work (and are tested)
without the optional ``[mesh]`` extra.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hico_plugin.errors import HicoError
from hico_plugin.storage import atomic_path


@dataclass
class TriangleMesh:
    """vertices: [V, 3] float64; faces: [F, 3] int64 vertex ids; vertex_colors: [V, 3] uint8 or None."""

    vertices: np.ndarray
    faces: np.ndarray
    vertex_colors: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        if self.vertex_colors is not None:
            self.vertex_colors = np.asarray(self.vertex_colors, dtype=np.uint8).reshape(-1, 3)
            if len(self.vertex_colors) != len(self.vertices):
                raise HicoError(f"mesh: {len(self.vertex_colors)} vertex colours for {len(self.vertices)} vertices")
        if len(self.faces) and (self.faces.min() < 0 or self.faces.max() >= len(self.vertices)):
            raise HicoError(f"mesh: face vertex ids must lie in [0, {len(self.vertices)}), got "
                            f"[{self.faces.min()}, {self.faces.max()}]")

    def face_areas(self) -> np.ndarray:
        """[F] triangle areas."""
        a, b, c = (self.vertices[self.faces[:, k]] for k in range(3))
        return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=-1)

    def subset(self, keep_faces: np.ndarray) -> TriangleMesh:
        """The faces where ``keep_faces`` ([F] bool) holds, with the vertices they reference only."""
        faces = self.faces[keep_faces]
        used = np.zeros(len(self.vertices), dtype=bool)
        used[faces.reshape(-1)] = True
        new_ids = np.cumsum(used) - 1
        colors = None if self.vertex_colors is None else self.vertex_colors[used]
        return TriangleMesh(self.vertices[used], new_ids[faces], colors)


def face_components(mesh: TriangleMesh) -> np.ndarray:
    """[F] id 0..K-1 of the connected component of each face (faces sharing a vertex are connected),
    numbered in the order of their lowest vertex id."""
    # Hooking and pointer jumping, as in Shiloach & Vishkin's parallel connectivity algorithm (J.
    # Algorithms 3, 1982), over the edges (v0, v1), (v0, v2) of every face: each round hooks every root
    # onto the smallest root an edge leads to, then flattens the trees. A tree with a neighbour merges
    # within two rounds, so O(log V) rounds of whole-array operations find every component.
    first, other = np.repeat(mesh.faces[:, 0], 2), mesh.faces[:, 1:].reshape(-1)
    root = np.arange(len(mesh.vertices))
    while True:
        a, b = root[first], root[other]
        if (a == b).all():
            break
        np.minimum.at(root, np.maximum(a, b), np.minimum(a, b))
        while (root[root] != root).any():
            root = root[root]
    return np.unique(root[mesh.faces[:, 0]], return_inverse=True)[1]


def clean_mesh(mesh: TriangleMesh, min_component_triangles: int) -> TriangleMesh:
    """Drop degenerate triangles (repeated vertex or zero area), then connected components with
    fewer than ``min_component_triangles`` triangles, then unreferenced vertices."""
    faces = mesh.faces
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    keep &= mesh.face_areas() > 0
    mesh = mesh.subset(keep)
    if min_component_triangles > 1 and len(mesh.faces):
        labels = face_components(mesh)
        sizes = np.bincount(labels)
        mesh = mesh.subset(sizes[labels] >= min_component_triangles)
    return mesh


def write_ply(path: str | Path, mesh: TriangleMesh) -> Path:
    """Write ``mesh`` as binary little-endian PLY (float32 xyz, uchar rgb when coloured), atomically."""
    vertex_fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if mesh.vertex_colors is not None:
        vertex_fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vertices = np.empty(len(mesh.vertices), dtype=vertex_fields)
    for k, axis in enumerate("xyz"):
        vertices[axis] = mesh.vertices[:, k]
    if mesh.vertex_colors is not None:
        for k, channel in enumerate(("red", "green", "blue")):
            vertices[channel] = mesh.vertex_colors[:, k]
    faces = np.empty(len(mesh.faces), dtype=[("n", "u1"), ("ids", "<i4", (3,))])
    faces["n"] = 3
    faces["ids"] = mesh.faces
    ply_type = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(vertices)}"]
    header += [f"property {ply_type[dtype]} {name}" for name, dtype in vertex_fields]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    with atomic_path(path) as tmp, tmp.open("wb") as handle:
        handle.write(("\n".join(header) + "\n").encode("ascii"))
        handle.write(vertices.tobytes())
        handle.write(faces.tobytes())
    return Path(path)


def read_ply(path: str | Path) -> TriangleMesh:
    """Read a triangle mesh file (PLY, OBJ, ... through trimesh) as a TriangleMesh."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise HicoError(f"{path}: mesh file not found")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as err:  # noqa: BLE001 - trimesh raises many types for malformed files
        raise HicoError(f"{path}: unreadable mesh file ({err})") from None
    colors = None
    visual = getattr(loaded, "visual", None)
    if visual is not None and getattr(visual, "kind", None) == "vertex":
        colors = np.asarray(visual.vertex_colors)[:, :3]
    return TriangleMesh(np.asarray(loaded.vertices), np.asarray(loaded.faces), colors)
