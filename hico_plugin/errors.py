"""User-facing errors: raised for bad input or configuration, printed by the CLIs as one line."""


class HicoError(Exception):
    """An error the user can fix (bad file, bad field, missing extra).

    The message must name the file or field and say what was expected; the command-line entry points
    print it as a single ``error: ...`` line and exit with a non-zero status instead of a traceback.
    """
