"""Per-chunk results on disk, so a long run that is killed can be resumed.

:func:`~torchflow.experiment.run_experiment` runs each filter over chunks of trials. With a
:class:`ChunkStore` it writes every finished chunk to a small file as soon as it finishes and,
when ``resume`` is on, loads the chunks a previous run of the *same settings* saved instead of
computing them again. Trials draw from per-trial random streams
(:class:`~torchflow.random.TrialStreams`), so a loaded chunk holds exactly the numbers the
uninterrupted run would have computed.

Layout (``key`` is a fingerprint of everything that changes a filter's numbers, see
:func:`fingerprint`)::

    <root>/<key>/settings.json          what the key was made of (for people)
    <root>/<key>/<start>-<stop>.pt       trials [start, stop): estimates, log-evidence, ESS, ...

Files are written to a temporary name and renamed, so a run killed while writing leaves no
half-written chunk. A file that cannot be read, or whose header does not match (other key, trials,
steps, seed, random stream, ...), is recomputed with a warning, never silently used.
"""
from __future__ import annotations

import hashlib
import json
import os
import warnings
from pathlib import Path
from typing import Dict, Mapping, Optional, Union

import torch

#: tensors of one chunk, CPU float64 (``ess``, ``g_eff``, ``n_repaired`` may be absent)
CHUNK_FIELDS = ("estimates", "log_evidence", "ess", "n_repaired", "g_eff")


def fingerprint(settings: Mapping) -> str:
    """A short, stable hash of JSON-serialisable ``settings`` (key order does not matter)."""
    text = json.dumps(settings, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


class ChunkStore:
    """Where a run keeps its finished chunks.

    Args:
        root: folder of the store (created on first save).
        keys: ``{filter name: key}``; the key names the filter's folder and must change with
            anything that changes its numbers (the runner uses :func:`fingerprint` of the model's
            and the filter's config, trials, steps, seed, device, dtype, random back end and the
            package versions). A filter without a key uses its name.
        resume: load chunks saved earlier; ``False`` computes every chunk and overwrites files.
        settings: ``{filter name: dict}`` written beside the chunks as ``settings.json``.

    Attributes ``loaded`` and ``computed`` count chunks per filter in this run.
    """

    def __init__(self, root: Union[str, Path], keys: Optional[Mapping[str, str]] = None, *, resume: bool = False,
                 settings: Optional[Mapping[str, dict]] = None):
        if not isinstance(resume, bool):
            raise ValueError(f"resume: expected True or False, got {resume!r}")
        self.root = Path(root)
        self.keys = dict(keys or {})
        self.resume = resume
        self.settings = dict(settings or {})
        self.loaded: Dict[str, int] = {}
        self.computed: Dict[str, int] = {}

    def folder(self, name: str) -> Path:
        return self.root / self.keys.get(name, name)

    def _path(self, name: str, start: int, stop: int) -> Path:
        return self.folder(name) / f"{start:07d}-{stop:07d}.pt"

    def load(self, name: str, start: int, stop: int, steps: int, meta: Optional[Mapping] = None) -> Optional[dict]:
        """The saved chunk of trials ``[start, stop)`` of filter ``name``, or ``None`` (not
        resuming, not saved, or saved with other settings). ``meta``: run settings the file's
        header must repeat (the runner passes seed, trials, steps, random stream, dtype, ...), a
        second guard beside the key for callers that choose their own keys."""
        if not self.resume:
            return None
        path = self._path(name, start, stop)
        if not path.exists():
            return None
        try:
            data = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # noqa: BLE001 - a damaged file is recomputed, not fatal
            warnings.warn(f"resume: cannot read {path} ({type(e).__name__}: {e}); computing the chunk again",
                          stacklevel=2)
            return None
        est = data.get("estimates")
        ok = (data.get("key") == self.keys.get(name, name) and data.get("start") == start and data.get("stop") == stop
              and isinstance(est, torch.Tensor) and tuple(est.shape[:2]) == (stop - start, steps)
              and (data.get("meta") is None or meta is None or data["meta"] == dict(meta)))  # no meta: older file
        if not ok:
            warnings.warn(f"resume: {path} was saved with other settings; computing the chunk again", stacklevel=2)
            return None
        self.loaded[name] = self.loaded.get(name, 0) + 1
        return data

    def save(self, name: str, start: int, stop: int, chunk: Mapping, meta: Optional[Mapping] = None) -> Path:
        """Write one finished chunk (CPU tensors and floats) atomically, with ``meta`` in its header."""
        folder = self.folder(name)
        folder.mkdir(parents=True, exist_ok=True)
        if name in self.settings and not (folder / "settings.json").exists():
            tmp = folder / f".settings.json.{os.getpid()}"
            tmp.write_text(json.dumps(self.settings[name], indent=2, sort_keys=True, default=str))
            os.replace(tmp, folder / "settings.json")
        path = self._path(name, start, stop)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        torch.save({**dict(chunk), "key": self.keys.get(name, name), "start": start, "stop": stop,
                    "meta": dict(meta) if meta is not None else None}, tmp)
        os.replace(tmp, path)
        self.computed[name] = self.computed.get(name, 0) + 1
        return path
