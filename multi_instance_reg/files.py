"""Checks on input files before a reader meets them, so that a wrong file gets a line naming it."""
from __future__ import annotations

from pathlib import Path

from .errors import InputError

ZIP_MAGIC = b"PK\x03\x04"   # an .npz is a zip archive


def require_npz_archive(path, what: str, remedy: str) -> Path:
    """``path`` as a Path once it is an existing, non-empty zip archive; else InputError naming
    ``what`` (e.g. "model file") and the file, then ``remedy``. numpy.load would call an empty
    file "No data left in file" and anything else "pickled data"."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} {path} does not exist; {remedy}")
    with open(path, "rb") as fh:
        head = fh.read(len(ZIP_MAGIC))
    if not head:
        raise InputError(f"{what} {path} is empty (0 bytes); {remedy}")
    if head != ZIP_MAGIC:
        raise InputError(f"{what} {path} is not a readable .npz (not a zip archive: it starts with {head!r}); {remedy}")
    return path
