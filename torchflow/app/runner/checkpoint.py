"""Per-chunk results on disk, so a killed run can be resumed (README, "Resumable runs")::

    <root>/<key>/settings.json          what the key (a :func:`fingerprint`) was made of (for people)
    <root>/<key>/<start>-<stop>.pt       trials [start, stop): estimates, log-evidence, ESS, ...

Files are written to a temporary name and renamed, and carry a SHA-256 checksum of their tensors;
a file that cannot be read, is damaged or whose header does not match is recomputed with a warning.
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
import warnings
from collections import Counter
from pathlib import Path
from typing import Callable, List, Mapping, Optional, Tuple, Union

import torch

from torchflow.app.runner.writers import replace_atomically, write_text
from torchflow.core import paths
from torchflow.core.errors import ArgumentError

#: tensors of one chunk, CPU (floats as float64), those the filter's result has: ``estimates (B, T, ...)``
#: always; ``estimate_mask`` (sets of estimates) and ``underflow`` from the localisers
CHUNK_FIELDS = (
    "estimates",
    "log_evidence",
    "ess",
    "n_repaired",
    "g_eff",
    "estimate_mask",
    "underflow",
    "std",
    "lost_at",
)
_CHUNK_NAME = re.compile(r"^(\d{7})-(\d{7})\.pt$")
log = logging.getLogger("torchflow.app.runner")


def _again(why: str) -> None:
    warnings.warn(f"{why}; computing the chunk again", stacklevel=3)


def checksum(chunk: Mapping) -> str:
    """SHA-256 of a chunk's tensors (names, dtypes, shapes and bytes), in name order."""
    h = hashlib.sha256()
    for name in sorted(k for k, v in chunk.items() if isinstance(v, torch.Tensor)):
        t = chunk[name].detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def fingerprint(settings: Mapping) -> str:
    """A short, stable hash of JSON-serialisable ``settings`` (key order does not matter)."""
    text = json.dumps(settings, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def fill_lost(chunks: List[dict]) -> Optional[str]:
    """Give the chunks whose every trial was lost (only ``lost_at``) the fields of the others,
    NaN (floats) or 0 in every row, and give every chunk a ``lost_at`` (zeros where none was
    lost), so that they concatenate. ``None``, or, when no chunk kept a trial, the error of the
    last: the filter has nothing to score."""
    template = next((c for c in chunks if "estimates" in c), None)
    if template is None:
        return next((c["error"] for c in reversed(chunks) if "error" in c), None)
    keys = [k for k in CHUNK_FIELDS if k in template]
    for c in chunks:
        n = c["stop"] - c["start"]
        for k in keys:
            if k not in c:
                v = template[k]
                c[k] = torch.full((n, *v.shape[1:]), float("nan") if v.is_floating_point() else 0, dtype=v.dtype)
        c.pop("error", None)
        c.setdefault("lost_at", torch.zeros(n, dtype=torch.long))
    return None


class ChunkStore:
    """Where a run keeps its finished chunks.

    Args:
        root: folder of the store (created on first save).
        keys: ``{filter name: key}`` naming each filter's folder (default: the name); the key must
            change with anything that changes its numbers (the command line's :func:`fingerprint`).
        resume: load chunks saved earlier; ``False`` computes every chunk and overwrites files.
        settings: ``{filter name: dict}`` written beside the chunks as ``settings.json``.

    ``loaded`` and ``computed`` count chunks per filter, ``reused_trials`` the trials taken from
    chunks of other boundaries; ``save_error`` says why saving stopped (else ``None``).
    """

    def __init__(
        self,
        root: Union[str, Path],
        keys: Optional[Mapping[str, str]] = None,
        *,
        resume: bool = False,
        settings: Optional[Mapping[str, dict]] = None,
    ):
        if not isinstance(resume, bool):
            raise ArgumentError(f"resume: expected True or False, got {resume!r}")
        self.root, self.keys, self.resume, self.settings = Path(root), dict(keys or {}), resume, dict(settings or {})
        self.loaded, self.computed, self.reused_trials = Counter(), Counter(), Counter()  # per filter
        self.save_error: Optional[str] = None

    def folder(self, name: str) -> Path:
        return self.root / self.keys.get(name, name)

    def _path(self, name: str, start: int, stop: int) -> Path:
        return self.folder(name) / f"{start:07d}-{stop:07d}.pt"

    def load(self, name: str, start: int, stop: int, steps: int, meta: Optional[Mapping] = None) -> Optional[dict]:
        """The saved chunk of trials ``[start, stop)`` of filter ``name``, or ``None`` (not resuming, not
        saved, or saved with other settings); ``meta``: run settings the file's header must repeat."""
        path = self._path(name, start, stop)
        if not self.resume or not (path.exists() or path.is_symlink()):
            return None
        if path.is_symlink() or not path.is_file():  # a chunk is a file this store wrote, never a link
            return _again(f"resume: {path} is not a regular file (a link or another kind of entry): not read")
        try:
            data = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:
            return _again(f"resume: cannot read {path} ({type(e).__name__}: {e})")
        est, lost = data.get("estimates"), data.get("lost_at")
        lost = lost > 0 if isinstance(lost, torch.Tensor) and tuple(lost.shape) == (stop - start,) else None
        all_lost = est is None and lost is not None and bool(lost.all())  # only lost_at: every trial lost
        ok = (
            data.get("key") == self.keys.get(name, name)
            and data.get("start") == start
            and data.get("stop") == stop
            and (all_lost or (isinstance(est, torch.Tensor) and tuple(est.shape[:2]) == (stop - start, steps)))
            and (data.get("meta") is None or meta is None or data["meta"] == dict(meta))
        )  # no meta: older file
        if not ok:
            return _again(f"resume: {path} was saved with other settings")
        if data.get("checksum") is not None and data["checksum"] != checksum(data):
            return _again(f"resume: {path} is damaged (its checksum does not match its contents)")
        logz = data.get("log_evidence")
        kept = slice(None) if lost is None else ~lost  # a lost trial's rows are NaN
        if not all_lost and (
            not bool(torch.isfinite(est[kept]).all())
            or (isinstance(logz, torch.Tensor) and bool(torch.isnan(logz[kept]).any()))
        ):
            # a run that computed these numbers would have marked the trial lost: not a chunk it saved
            return _again(f"resume: {path} holds NaN or infinite estimates in trials not marked lost")
        self.loaded[name] += 1
        return data

    def save(
        self, name: str, start: int, stop: int, chunk: Mapping, meta: Optional[Mapping] = None, computed: bool = True
    ) -> Path:
        """Write one finished chunk (CPU tensors and floats) atomically, with ``meta`` in its header;
        ``computed``: it was computed here (counted in :attr:`computed`), not put together from
        chunks saved with other boundaries (:meth:`assemble`, counted in :attr:`reused_trials`)."""
        folder = self.folder(name)
        folder.mkdir(parents=True, exist_ok=True)
        if name in self.settings and not (folder / "settings.json").exists():
            write_text(folder / "settings.json", json.dumps(self.settings[name], indent=2, sort_keys=True, default=str))
        path = self._path(name, start, stop)
        record = {
            **dict(chunk),
            "key": self.keys.get(name, name),
            "start": start,
            "stop": stop,
            "meta": dict(meta) if meta is not None else None,
            "checksum": checksum(chunk),
        }
        replace_atomically(path, lambda fh: torch.save(record, fh), binary=True)  # never through a link
        if computed:
            self.computed[name] += 1
        return path

    def save_or_warn(
        self, name: str, start: int, stop: int, chunk: Mapping, meta: Optional[Mapping] = None, computed: bool = True
    ) -> Optional[Path]:
        """:meth:`save`, but a store that cannot write warns once and saves nothing more."""
        if self.save_error is not None:
            return None
        try:
            return self.save(name, start, stop, chunk, meta, computed)
        except OSError as e:
            self.save_error = f"{type(e).__name__}: {e.strerror or e}"
            warnings.warn(
                f"checkpoint_dir: cannot save chunks under {self.root} ({self.save_error}); the run "
                "goes on without checkpoints (a later resume computes these chunks again)",
                stacklevel=2,
            )
            return None

    def saved_ranges(self, name: str) -> List[Tuple[int, int]]:
        """``[(start, stop), ...]`` of the chunk files saved for filter ``name``."""
        folder = self.folder(name)
        if not folder.is_dir():
            return []
        found = (_CHUNK_NAME.match(p.name) for p in folder.iterdir())
        return sorted((int(m.group(1)), int(m.group(2))) for m in found if m)

    def assemble(
        self,
        name: str,
        start: int,
        stop: int,
        steps: int,
        meta: Optional[Mapping],
        compute: Callable[[int, int], Mapping],
    ) -> Optional[dict]:
        """Trials ``[start, stop)`` from chunks saved with other boundaries, ``compute(a, b)``
        filling the trials none holds; ``None`` when not resuming or no saved trial overlaps."""
        saved = [
            r
            for r in (self.saved_ranges(name) if self.resume else [])
            if r[0] < stop and r[1] > start and r != (start, stop)
        ]
        if not saved:
            return None
        pieces, p = [], start  # (a, b, the saved range holding trials [a, b) or None): saved trials and the gaps
        while p < stop:
            cover = max((r for r in saved if r[0] <= p < r[1]), key=lambda r: r[1], default=None)
            b = min(cover[1], stop) if cover else min([r[0] for r in saved if r[0] > p] + [stop])
            pieces.append((p, b, cover))
            p = b
        parts, reused = [], 0
        for a, b, r in pieces:
            data = None if r is None else self.load(name, r[0], r[1], steps, meta)
            if data is None:
                parts.append(dict(compute(a, b)))
                continue
            part = {k: data[k][a - r[0] : b - r[0]] for k in CHUNK_FIELDS if k in data}
            part.update(start=a, stop=b)
            part["elapsed"] = float(data.get("elapsed", 0.0)) * (b - a) / (r[1] - r[0])
            part["paths"] = data.get("paths")  # the paths of the run that computed the saved chunk (its counts)
            parts.append(part)
            reused += b - a
        error = fill_lost(parts)  # lost trials: every part gets lost_at, and a part whose trials were all lost NaN rows
        chunk = {k: torch.cat([p[k] for p in parts]) for k in CHUNK_FIELDS if all(k in p for p in parts)}
        if error is not None:
            chunk["error"] = error
        chunk.update(
            start=start,
            stop=stop,
            elapsed=sum(float(p["elapsed"]) for p in parts),
            paths=paths.merge(*(p.get("paths") for p in parts)),
        )
        self.reused_trials[name] += reused
        log.info(
            "resume: %s trials %d..%d: %d reused from chunks saved with other boundaries, %d computed",
            name,
            start,
            stop - 1,
            reused,
            stop - start - reused,
        )
        return chunk
