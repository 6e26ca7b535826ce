"""Resuming a run: each finished task's result in ``OUT/parts/<task>.json``, and the settings
they were made with in ``OUT/parts/run.json``; a rerun with the same settings skips them."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from ..errors import InputError


def model_hash(model) -> str:
    """A short digest of a model's name and point sets: a changed model is another run."""
    h = hashlib.sha1(model.name.encode())
    for name in ("points_xyz", "keypoints_xyz", "descriptors", "shape_points"):
        arr = getattr(model, name, None)
        if arr is not None:
            h.update(np.ascontiguousarray(arr).tobytes())
    return h.hexdigest()[:16]


def run_fingerprint(models, config, tracker_config, **extra) -> dict:
    """What a run's results depend on: the models, the pipeline's and the tracker's settings
    (None: no tracking) and ``extra`` (the data, the scoring options), as plain JSON."""
    from ..params import flatten

    settings = {**extra, "models": [model_hash(m) for m in models], "params": flatten(config),
                "tracking": None if tracker_config is None else flatten(tracker_config)}
    return json.loads(json.dumps(settings, default=list))


class PartsFolder:
    """``OUT/parts/``: one JSON file per finished task and ``run.json`` with the settings
    they were made with. A rerun with other settings is refused rather than mixed."""

    def __init__(self, folder: Path, fingerprint: dict):
        self.folder = Path(folder)
        record = self.folder / "run.json"
        if record.is_file():
            try:
                before = json.loads(record.read_text())
            except ValueError:
                before = None
            if before != fingerprint:
                differ = sorted(k for k in fingerprint if not isinstance(before, dict) or before.get(k) != fingerprint[k])
                raise InputError(f"{self.folder} holds the parts of a run with other settings (differing: "
                                 f"{', '.join(differ) or 'the record'}); give a new output folder or delete {self.folder}")
        self.folder.mkdir(parents=True, exist_ok=True)
        record.write_text(json.dumps(fingerprint, indent=1))

    def path(self, key: str) -> Path:
        return self.folder / f"{key}.json"

    def load(self, key: str) -> dict | None:
        try:
            return json.loads(self.path(key).read_text())
        except (OSError, ValueError):       # absent, or cut short by a crash: run it again
            return None

    def save(self, key: str, result: dict) -> None:
        """``result`` without its "overlays" / "files" (bytes, written where they belong)."""
        tmp = self.path(key).with_suffix(".tmp")
        tmp.write_text(json.dumps({k: v for k, v in result.items() if k not in ("overlays", "files")}))
        tmp.replace(self.path(key))        # whole or not at all
