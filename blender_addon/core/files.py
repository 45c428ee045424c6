"""Atomic file writes and all-or-nothing output folders (pure Python, no bpy)."""

from __future__ import annotations

import json
import os
import secrets
import shutil
import tempfile
from collections.abc import Iterable
from typing import Any

import numpy as np


def atomic_write_bytes(path: str, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file in the same folder and ``os.replace``."""
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{os.path.basename(path)}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str, text: str) -> None:
    """UTF-8 text, atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def json_text(obj: Any) -> str:
    """Indented JSON in which each numpy array is one compact line (a mesh's vertices).

    Indenting takes Python's pure-Python encoder: a million-triangle mesh as nested lists
    took ≈ 20 s and 85 MB. The arrays are set aside, the rest indented, and each array
    written by the C encoder in its place. NaN is refused (the scene format has none).
    """
    arrays: list[np.ndarray] = []
    token = secrets.token_hex(8)  # no string of the scene can be mistaken for a placeholder

    def set_aside(o: Any) -> Any:
        if isinstance(o, np.ndarray):
            arrays.append(o)
            return f"\0{token}\0"
        if isinstance(o, dict):
            return {k: set_aside(v) for k, v in o.items()}
        if isinstance(o, (list, tuple)):
            return [set_aside(v) for v in o]
        return o

    text = json.dumps(set_aside(obj), indent=1, allow_nan=False)
    compact = (json.dumps(a.tolist(), allow_nan=False, separators=(",", ":")) for a in arrays)
    # One pass: the placeholders in order (json.dumps writes the NUL as \u0000).
    parts = text.split(json.dumps(f"\0{token}\0"))
    return "".join(p + next(compact, "") for p in parts) + "\n"


def atomic_write_json(path: str, obj: Any) -> None:
    """:func:`json_text` of ``obj``, atomically."""
    atomic_write_text(path, json_text(obj))


class Staging:
    """A hidden folder inside the output folder where a job writes its files.

    :meth:`commit` moves the named files into the output folder with ``os.replace`` (atomic
    per file, same file system) and removes the staging folder; :meth:`discard` removes it
    without touching the output folder. Until ``commit`` nothing visible is written.
    """

    def __init__(self, directory: str) -> None:
        self.directory = os.path.abspath(directory)
        os.makedirs(self.directory, exist_ok=True)
        self.path = tempfile.mkdtemp(dir=self.directory, prefix=".tyndall-staging-")

    def file(self, name: str) -> str:
        """Path of ``name`` (may contain ``/``) inside the staging folder; parent folders are made."""
        p = os.path.join(self.path, name)
        os.makedirs(os.path.dirname(p), exist_ok=True)
        return p

    def commit(self, names: Iterable[str] | None = None) -> list[str]:
        """Move ``names`` (default: every file staged) into the output folder; returns the final paths."""
        if names is None:
            names = [
                os.path.relpath(os.path.join(root, f), self.path)
                for root, _dirs, files in os.walk(self.path)
                for f in files
            ]
        names = sorted(names)
        for n in names:
            if not os.path.isfile(os.path.join(self.path, n)):
                raise FileNotFoundError(f"staged file missing: {n}")
        out = []
        for n in names:
            dst = os.path.join(self.directory, n)
            os.makedirs(os.path.dirname(dst), exist_ok=True)
            os.replace(os.path.join(self.path, n), dst)
            out.append(dst)
        self.discard()
        return out

    def discard(self) -> None:
        """Remove the staging folder and everything in it."""
        shutil.rmtree(self.path, ignore_errors=True)
