"""The command shell every torchflow command runs in: ``torchflow`` (:mod:`torchflow.app.cli`, the
runs) and ``torchflow-learn`` (:mod:`torchflow.app.learn`, maximum-likelihood fits) are each a
:class:`Command` (a Hydra config and a job function) started by :func:`main`, which gives them
one set of contracts:

Settings
    A group selection naming no config (``filter=[nope]``) or one config twice (``filter=[bpf,bpf]``),
    a key the command's config does not have (``+learning_rate=0.5``, or ``n_particle=7`` without
    ``+``, which Hydra refuses), an override Hydra's grammar cannot read (``label=ünï码`` unquoted:
    the line shows the quoted form) or a bad value is refused before anything runs: one line on
    stderr (an unknown key names the closest known ones: ``did you mean lr?``), exit status 2.
    Hydra's own errors reach :func:`main` (:func:`hydra_error`) instead of being printed by Hydra.

Output folder (Hydra's resolved ``hydra.run.dir`` / ``hydra.sweep.dir``, however it was quoted)
    :class:`OutputGuard`, a Hydra callback of both configs, checks it before Hydra writes anything
    into it, and refuses in one line (exit 2): a folder that cannot be written; a folder a live
    run holds (its lock file :data:`LOCK_NAME` names the process); a folder holding an earlier
    run's results (any command's :data:`~torchflow.app.runner.writers.ALL_RESULT_FILES`; a sweep's
    job folders: :func:`earlier_jobs`) unless ``overwrite=true`` (or ``resume=true``) says to replace
    them, which clears them first (a sweep's earlier job folders are removed with ``overwrite=true``).
    The lock file holds the process id; it is created atomically (``O_CREAT | O_EXCL``) and removed
    when the process exits, so two runs into one folder never both go on; a lock left by a process
    that is gone is taken over with a warning. Nothing is created before the checks but the folder
    Hydra creates anyway. A full disk when Hydra then writes ``.hydra/`` is one line naming the
    folder (exit status 1).

Signals
    SIGINT (Ctrl-C) and SIGTERM (``kill``, a scheduler's time limit) are stop requests
    (:data:`~torchflow.app.runner.STOP`): the job stops at its next safe point (a run: at once inside
    a chunk of trials, keeping the finished chunks; learning: after the current optimiser step),
    writes the results of what finished, and exits with ``128 + the signal``: 130 (SIGINT), 143
    (SIGTERM). A further signal changes nothing (SIGKILL ends a process without results). In a
    sweep, a stop request ends the sweep (a launcher's worker lets its job return, and starts no
    other), which ends with its report and the command that goes on (exit status 130 / 143).

Job environment
    :func:`job_environment`: the device and dtype checked, the torch threads (``threads``;
    :func:`job_threads`) and the speed knobs (``tuning.*``, :mod:`torchflow.core.tuning`) set for the
    job and restored after it.

Exit status (every command): 0 done; 1 a failure (a filter failed, the results could not be
written, or any other error, which keeps its traceback); 2 a configuration error or a refused
output folder (one line); 130 stopped by SIGINT (Ctrl-C); 143 stopped by SIGTERM.
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import logging
import os
import shutil
import signal
import socket
import sys
import tempfile
import time
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from torchflow.app.runner import config as rc
from torchflow.app.runner.execute import STOP
from torchflow.app.runner.plan import ConfigError, resolve_device, resolve_dtype
from torchflow.app.runner.writers import ALL_RESULT_FILES, exclusive_temp
from torchflow.core import tuning
from torchflow.core.registry import register_configs

log = logging.getLogger("torchflow.shell")

#: the lock file a live run keeps in its output folder (its process id, host and command)
LOCK_NAME = ".torchflow.lock"
#: exit statuses: done, a failure, a configuration error (SIGINT / SIGTERM: 128 + the signal)
EXIT_OK, EXIT_FAILED, EXIT_CONFIG = 0, 1, 2


@dataclass(frozen=True)
class Command:
    """One command of the shell.

    Attributes:
        prog: its name in messages and in the resume hint (``torchflow``).
        config_name: its primary Hydra config (``configs/<config_name>.yaml``).
        job: ``job(cfg, out, env) -> exit status``: the work, given the checked config, the
            output folder (created, cleared of earlier results) and the :class:`JobEnv`; it polls
            :data:`~torchflow.app.runner.STOP` and returns ``STOP.exit_code`` when it stopped early.
        free_form: top-level subtrees of the config whose keys are constructor arguments (not
            checked against the YAML).
        distributed: whether ``torchrun`` may start it (ranks other than 0 write into a
            temporary folder; rank 0 alone is guarded).
        resumable: whether ``resume=true`` goes on from saved chunks (a stopped sweep's end then
            prints the command that goes on).
    """

    prog: str
    config_name: str
    job: Callable[[DictConfig, Path, "JobEnv"], int]
    free_form: Sequence[str] = rc.FREE_FORM
    distributed: bool = False
    resumable: bool = False


def config_error(e: BaseException) -> Optional[str]:
    """The one-line message of a bad setting: ours, OmegaConf's, or a ``ValueError`` / ``TypeError`` of
    a constructor Hydra calls (named by its key); ``None`` for anything else (a failure)."""
    if not isinstance(e, InstantiationException):
        return str(e) if isinstance(e, (ConfigError, OmegaConfBaseException)) else None
    cause = e.__cause__ or e.__context__
    if not isinstance(cause, (ValueError, TypeError)):
        return None
    key = [ln.split(":", 1)[1].strip() + ": " for ln in str(e).splitlines() if ln.startswith("full_key:")]
    text = str(cause)
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":  # a KeyError's quotes, both ends only
        text = text[1:-1]
    return (key[-1] if key else "") + text


def multirun() -> bool:
    """Whether this job is one of a sweep's (``-m``)."""
    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


# ----------------------------------------------------------------------------------------------
# job environment: device, dtype, threads, speed knobs


def job_threads(threads=None) -> Optional[int]:
    """Torch threads of one job (numpy's random fills use as many): ``threads`` when given (a
    positive int); else, when ``OMP_NUM_THREADS`` is set, ``None`` (torch already follows it); else
    the cores this process may use divided among the jobs a Hydra launcher runs at once (the joblib
    launcher's ``n_jobs``; 1 for the sequential one), at least 1. Side by side with default threads,
    two torch processes each take every core and slow each other down many times over."""
    if threads is not None:
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise ConfigError(f"threads: expected a positive number of threads or null, got {threads!r}")
        return threads
    if os.environ.get("OMP_NUM_THREADS"):
        return None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    jobs = 1
    if multirun():
        n_jobs = OmegaConf.select(HydraConfig.get(), "launcher.n_jobs", default=None)
        if isinstance(n_jobs, int) and n_jobs != 1:
            jobs = cores if n_jobs < 1 else n_jobs  # joblib: -1 means one job per core
    return max(1, cores // jobs)


@contextlib.contextmanager
def torch_threads(n: Optional[int]):
    """``torch.set_num_threads(n)`` for the job (``None``: unchanged), restored after it."""
    before = torch.get_num_threads()
    if n is not None and n != before:
        torch.set_num_threads(n)
        log.debug(f"torch threads: {n}")
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)


@dataclass(frozen=True)
class JobEnv:
    """What :func:`job_environment` set up: the checked ``device`` and ``dtype`` (``None`` where
    the command's config has no such key), the torch ``threads`` in force, the ``tuning`` knobs."""

    device: Optional[torch.device]
    dtype: Optional[torch.dtype]
    threads: int
    tuning: Dict[str, int]


@contextlib.contextmanager
def job_environment(cfg: DictConfig):
    """For the job: ``device`` and ``dtype`` checked (a bad one, or ``cuda`` without a GPU: a
    :class:`ConfigError`), the speed knobs of ``tuning`` set (null: the measured default; an unknown
    or bad knob: a :class:`ConfigError`), torch threads from ``threads`` (:func:`job_threads`);
    all restored afterwards. Yields a :class:`JobEnv`."""
    device = resolve_device(cfg.device) if "device" in cfg else None
    dtype = resolve_dtype(cfg.dtype) if "dtype" in cfg else None
    given = cfg.get("tuning") or {}
    knobs = {
        k: v
        for k, v in (OmegaConf.to_container(given) if OmegaConf.is_config(given) else dict(given)).items()
        if v is not None
    }
    with contextlib.ExitStack() as stack:
        try:
            stack.enter_context(tuning.tuned(**knobs))
        except (ValueError, TypeError) as e:
            raise ConfigError(str(e)) from None
        stack.enter_context(torch_threads(job_threads(cfg.get("threads"))))
        yield JobEnv(device, dtype, torch.get_num_threads(), tuning.as_dict())


class Output:
    """Writes into the job's folder: the first failed write (read-only folder, full disk) is reported
    in one line and turns the exit status to 1 (:attr:`failed` says why); nothing more is
    written, the job goes on."""

    def __init__(self, out: Path):
        self.out, self.failed = out, None

    def attempt(self, what: str, write, *args) -> None:
        try:
            if self.failed is None:
                write(*args)
        except OSError as e:
            self.failed = f"cannot write {what} into {self.out} ({type(e).__name__}: {e.strerror or e})"
            log.error(f"error: {self.failed}")


# ----------------------------------------------------------------------------------------------
# the output folder: its lock file and the earlier results it may hold


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    except OSError:
        return False
    return True


def _started_after(pid: int, when: float) -> bool:
    """Whether process ``pid`` started after time ``when`` (so it reused a dead holder's id);
    ``False`` where it cannot be told (no ``/proc``)."""
    try:
        ticks = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19])
        boot = next(
            float(ln.split()[1]) for ln in Path("/proc/stat").read_text().splitlines() if ln.startswith("btime")
        )
        return boot + ticks / os.sysconf("SC_CLK_TCK") > when + 2.0
    except (OSError, ValueError, IndexError, StopIteration):
        return False


def _read_lock(path: Path) -> Optional[dict]:
    """``{pid, host, command, mtime}`` of a lock file; ``None`` if there is none."""
    try:
        text, mtime = path.read_text(), path.stat().st_mtime
    except FileNotFoundError:
        return None
    except OSError:
        text, mtime = "", time.time()
    lines = text.splitlines()
    try:
        pid = int(lines[0])
    except (IndexError, ValueError):
        pid = None
    return {
        "pid": pid,
        "host": lines[1] if len(lines) > 1 else "",
        "command": lines[2] if len(lines) > 2 else "",
        "mtime": mtime,
    }


def _holder_alive(info: dict) -> bool:
    """Whether the process a lock names still runs: its pid alive on this host (and not a newer
    process that reused the id); a lock of another host counts as alive (it cannot be checked);
    an empty lock younger than 10 s is being written (alive), an older one is debris."""
    if info["pid"] is None:
        return time.time() - info["mtime"] < 10.0
    if info["host"] and info["host"] != socket.gethostname():
        return True
    return _pid_alive(info["pid"]) and not _started_after(info["pid"], info["mtime"])


class OutputLock:
    """The lock file :data:`LOCK_NAME` of an output folder, held by this process from
    :meth:`acquire` to :meth:`release` (at the latest when the process exits).

    :meth:`acquire` creates it with ``O_CREAT | O_EXCL`` and writes the process id, host and
    command; if it exists and its process is alive (:func:`_holder_alive`), a
    :class:`ConfigError` names that process; if its process is gone, the lock is taken over and
    :attr:`took_over` describes the stale one (the caller warns; the takeover is serialised by an
    ``flock`` on the folder, so of two processes taking over one stale lock, one gets it and the
    other is refused)."""

    def __init__(self, folder: Path, key: str = "hydra.run.dir", command: str = "torchflow"):
        self.folder, self.key, self.command = Path(folder), key, command
        self.path, self.held, self.took_over = self.folder / LOCK_NAME, False, None

    def takeover_message(self) -> Optional[str]:
        """The warning about the stale lock this lock replaced (``None``: none)."""
        if self.took_over is None:
            return None
        who = f"pid {self.took_over['pid']}" if self.took_over["pid"] is not None else "an unreadable lock"
        return (
            f"{self.key}: took over the stale lock {self.path} of a run that is gone ({who}); its results, "
            "if any, count as an earlier run's"
        )

    def acquire(self) -> "OutputLock":
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                fd = None
            except OSError as e:
                raise ConfigError(
                    f"{self.key}: cannot create the lock file {self.path} ({type(e).__name__}: "
                    f"{e.strerror or e}); choose a writable folder with {self.key}=<folder>"
                ) from None
            if fd is None:
                info = _read_lock(self.path)
                if info is None:
                    continue  # removed meanwhile: try again
                if info["pid"] == os.getpid() and info["host"] in ("", socket.gethostname()):
                    self.held = True  # this process holds it already (a second job of one process)
                    _HELD.setdefault(self.path, self)
                    return self
                if _holder_alive(info):
                    who = f"pid {info['pid']}" if info["pid"] is not None else "a process starting"
                    host = f" on {info['host']}" if info["host"] and info["host"] != socket.gethostname() else ""
                    raise ConfigError(
                        f"{self.key}: {self.folder} is in use by a running torchflow command ({who}{host}"
                        f"{', ' + info['command'] if info['command'] else ''}; lock file {self.path}); wait for it to "
                        f"finish or choose another folder ({self.key}=<new folder>)"
                    )
                if self._remove_stale(info):
                    self.took_over = info
                continue
            with os.fdopen(fd, "w") as fh:
                fh.write(f"{os.getpid()}\n{socket.gethostname()}\n{self.command}\n")
            self.held = True
            _HELD[self.path] = self
            return self
        raise ConfigError(
            f"{self.key}: cannot take the lock {self.path} (other runs keep taking it); "
            f"choose another folder ({self.key}=<new folder>)"
        )

    def _remove_stale(self, info: dict) -> bool:
        """Remove the lock if it still is the stale one ``info`` describes (under an ``flock`` of
        the folder, so that two processes never both remove and recreate it)."""
        with _folder_mutex(self.folder):
            now = _read_lock(self.path)
            if now is None or (now["pid"], now["host"], now["mtime"]) != (info["pid"], info["host"], info["mtime"]):
                return False
            self.path.unlink(missing_ok=True)
            return True

    def release(self) -> None:
        """Remove the lock file if this process still holds it."""
        if not self.held:
            return
        self.held = False
        _HELD.pop(self.path, None)
        info = _read_lock(self.path)
        if info is not None and info["pid"] == os.getpid():
            with contextlib.suppress(OSError):
                self.path.unlink()


#: the locks this process holds (released at exit)
_HELD: Dict[Path, OutputLock] = {}
#: what :class:`OutputGuard` checked in this process: ``hydra.run.dir`` / ``hydra.sweep.dir`` -> the
#: folder, and a sweep's ``checkpoint_dir`` (for the messages of :func:`main`)
GUARDED: Dict[str, object] = {}


@contextlib.contextmanager
def _folder_mutex(folder: Path):
    try:
        import fcntl
    except ImportError:  # no flock (Windows): the takeover race stays, the O_EXCL create does not
        yield
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def release_locks() -> None:
    """Release every lock this process holds (at exit, and when :func:`main` returns)."""
    for lock in list(_HELD.values()):
        lock.release()


atexit.register(release_locks)


def earlier_jobs(folder: Path) -> List[Path]:
    """The job folders an earlier sweep left in the sweep folder ``folder``: numbered folders holding
    Hydra's ``.hydra`` or a result file (a finished, failed, stopped or killed job)."""
    from torchflow.app.runner.sweep import job_dirs

    return [j for j in job_dirs(folder) if (j / ".hydra").is_dir() or any((j / n).exists() for n in ALL_RESULT_FILES)]


def earlier_results(folder: Path, sweep: bool = False) -> List[str]:
    """The result files an earlier run left in ``folder``, relative to it (a sweep folder: its jobs'
    ``results.json``, ``learn.csv`` and ``error.txt``, and ``<job>/`` for a job folder holding none:
    a job killed or stopped before it wrote any)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    if sweep:
        found = []
        for job in earlier_jobs(folder):
            files = [f"{job.name}/{n}" for n in ("results.json", "learn.csv", "error.txt") if (job / n).exists()]
            found += files or [f"{job.name}/"]
        return found
    return [n for n in ALL_RESULT_FILES if (folder / n).exists()]


#: what Hydra and the log write into a run's folder (not through the result writers' exclusive files)
HYDRA_WRITES = (".hydra", "multirun.yaml")


def _links_at_writes(folder: Path) -> List[Path]:
    """Links in ``folder`` at names that Hydra or the run's log write with a plain ``open``: the
    ``.hydra`` folder and its files, ``multirun.yaml`` and the ``*.log`` files; and a ``.hydra``
    folder another user owns (who could put links into it after this check)."""
    names = [folder / n for n in HYDRA_WRITES] + sorted(folder.glob("*.log"))
    found = [p for p in names if p.is_symlink()]
    hydra = folder / ".hydra"
    if hydra.is_dir() and not hydra.is_symlink():
        if hasattr(os, "getuid") and hydra.stat().st_uid != os.getuid():  # another user could plant links later
            found.append(hydra)
        found += sorted(p for p in hydra.iterdir() if p.is_symlink())
    return found


def planted_links(folder: Path, sweep: bool = False) -> List[Path]:
    """The links a run in ``folder`` would write through (:func:`_links_at_writes`); for a sweep
    folder also those of its existing job folders, and job folders that are links themselves."""
    folder = Path(folder)
    found = _links_at_writes(folder)
    if sweep:
        for job in sorted(p for p in folder.iterdir() if p.name.isdigit()):
            found += [job] if job.is_symlink() else _links_at_writes(job) if job.is_dir() else []
    return found


def guard_output_folder(
    folder: Path,
    *,
    key: str = "hydra.run.dir",
    shown: Optional[str] = None,
    replace: bool = False,
    sweep: bool = False,
    clear_jobs: bool = False,
    command: str = "torchflow",
) -> OutputLock:
    """Make ``folder`` ready for a run, or raise a one-line :class:`ConfigError`: it must be
    writable (created if missing), no live run may hold it, and it must hold no earlier results
    unless ``replace`` (``overwrite=true`` / ``resume=true``). A sweep folder (``sweep``) with
    ``clear_jobs`` (``overwrite=true``) is cleared of the earlier sweep's job folders and
    ``sweep_summary.csv``, so that the end report and ``collect.py`` see this sweep's jobs alone
    (``resume=true`` reruns the same jobs into their folders). Returns its held :class:`OutputLock`.
    ``shown``: the folder as the user gave it (for messages; default ``folder``)."""
    folder, shown = Path(folder), shown or str(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = exclusive_temp(folder / ".torchflow-write-test")  # created exclusively: no link followed
        os.close(fd)
        probe.unlink()
    except OSError as e:
        raise ConfigError(
            f"{key}: cannot write into {folder} ({type(e).__name__}: {e.strerror or e}); choose a "
            f"writable folder with {key}=<folder>"
        ) from None
    links = planted_links(folder, sweep)
    if links:  # Hydra's own writes (.hydra/*.yaml) would follow them: refused, never written through
        shown_links = ", ".join(
            f"{p.relative_to(folder)} -> {os.readlink(p)}"
            if p.is_symlink()
            else f"{p.relative_to(folder)} (another user's)"
            for p in links[:3]
        )
        raise ConfigError(
            f"{key}: {shown} holds links at names a run writes itself ({shown_links}"
            f"{', ...' if len(links) > 3 else ''}); a run would write through them into their targets: remove "
            f"the links or choose another folder ({key}=<new folder>)"
        )
    lock = OutputLock(folder, key, command).acquire()
    found = earlier_results(folder, sweep)
    if found and not replace:
        lock.release()
        what = "the jobs of an earlier sweep" if sweep else "the results of a run"
        raise ConfigError(
            f"{key}: {shown} already holds {what} ({', '.join(found[:4])}"
            f"{', ...' if len(found) > 4 else ''}); choose a new folder ({key}=<new folder>) or add "
            "overwrite=true to replace them"
        )
    if sweep and clear_jobs:
        jobs = earlier_jobs(folder)
        for job in jobs:
            shutil.rmtree(job, ignore_errors=True)
        (folder / "sweep_summary.csv").unlink(missing_ok=True)
        if jobs:  # said, not silent: overwrite=true removed another sweep's finished work
            print(
                f"warning: overwrite=true: removed {len(jobs)} job folder(s) of an earlier sweep from {shown} "
                f"({', '.join(Path(j).name for j in jobs[:6])}{', ...' if len(jobs) > 6 else ''})",
                file=sys.stderr,
            )
    return lock


class OutputGuard(Callback):
    """Hydra callback (``hydra.callbacks.output_guard`` of every command's config): before Hydra
    creates and writes into the run's (sweep's) folder, resolve it as Hydra will (its interpolations
    and quoting) and :func:`guard_output_folder` it; a refusal is one line on stderr and exit 2. Ranks
    other than 0 of a ``torchrun`` run write into their own temporary folders and are not guarded."""

    def _guard(self, config: DictConfig, key: str, sweep: bool) -> None:
        if int(os.environ.get("RANK", "0") or 0):
            return
        try:
            HydraConfig.instance().set_config(config)  # ${hydra:...} in the folder's name
            given = str(OmegaConf.select(config, key))
            overwrite, resume = (OmegaConf.select(config, k, default=False) is True for k in ("overwrite", "resume"))
            folder = Path(given) if Path(given).is_absolute() else Path.cwd() / given
            lock = guard_output_folder(
                folder,
                key=key,
                shown=given,
                replace=overwrite or resume,
                sweep=sweep,
                clear_jobs=overwrite,
                command=os.environ.get(rc.PROG_ENV, "torchflow"),
            )
            GUARDED[key] = folder
            if sweep:  # a stopped sweep's end tells how to go on only where chunks were saved
                GUARDED["checkpoint_dir"] = OmegaConf.select(config, "checkpoint_dir", default=None)
            if lock.took_over is not None:
                print(f"warning: {lock.takeover_message()}", file=sys.stderr)
        except (ConfigError, OmegaConfBaseException) as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(EXIT_CONFIG)

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        self._guard(config, "hydra.run.dir", sweep=False)

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        self._guard(config, "hydra.sweep.dir", sweep=True)

    def on_run_end(self, config: DictConfig, **kwargs) -> None:
        release_locks()

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        release_locks()


# ----------------------------------------------------------------------------------------------
# signals, the job, the Hydra entry, main


def install_stop_handlers() -> bool:
    """SIGINT and SIGTERM become stop requests (:data:`~torchflow.app.runner.STOP`); ``False`` where
    handlers cannot be set (not the main thread: Python's own Ctrl-C handling only)."""
    try:
        signal.signal(signal.SIGINT, STOP.handler)
        signal.signal(signal.SIGTERM, STOP.handler)
    except ValueError:
        return False
    return True


def run_job(command: Command, cfg: DictConfig) -> int:
    """One job of ``command``: check the config (unknown keys, values), then in the job environment
    (:func:`job_environment`) with the output folder created and cleared of earlier results, the
    command's job; its exit status. A stop request that came before the job started ends it at once."""
    rc.check_config(cfg, HydraConfig.get().runtime.choices, command.config_name, command.free_form)
    if STOP.requested:
        log.warning(f"stopped ({STOP.name}) before the job started: nothing was run")
        return STOP.exit_code
    out = Path(HydraConfig.get().runtime.output_dir)
    with job_environment(cfg) as env:
        out.mkdir(parents=True, exist_ok=True)
        # a reused folder (overwrite=true / resume=true) keeps no old result file
        from torchflow.app.runner.writers import clear_results

        clear_results(out)
        return command.job(cfg, out, env)


def _job(command: Command, cfg: DictConfig) -> int:
    """:func:`run_job` with its errors turned into messages and exit statuses."""
    try:
        return run_job(command, cfg)
    except KeyboardInterrupt:  # a stop the job did not catch (raised by Python's own handler)
        if not STOP.requested:
            STOP.handler(signal.SIGINT, None)
        log.warning(
            f"interrupted ({STOP.name}) outside the job's safe points: only the results written before it are there"
        )
        return STOP.exit_code
    except Exception as e:
        bad = config_error(e)
        if bad is not None:
            message, code = f"error: {bad}", EXIT_CONFIG
            log.error(message + (" (job failed; the sweep goes on)" if multirun() else ""))
        else:
            message, code = traceback.format_exc(), EXIT_FAILED
            log.error(f"error: {type(e).__name__}: {e}\n{message.rstrip()}")
        if multirun():  # the job's error.txt (collect and the end-of-sweep report name it); the sweep goes on
            out = Path(HydraConfig.get().runtime.output_dir)
            with contextlib.suppress(OSError):
                out.mkdir(parents=True, exist_ok=True)
                from torchflow.app.runner.writers import write_text

                write_text(out / "error.txt", message.rstrip() + "\n")
        return code


def shown_path(path) -> str:
    """``path`` as the user should read it: relative to the folder the command was started in
    (Hydra's ``hydra.job.chdir=true`` moves the job into its output folder, where a plain relative
    path would print as ``.``), absolute when it lies outside that folder."""
    try:
        from hydra.utils import get_original_cwd

        start = get_original_cwd()
    except (ImportError, ValueError):  # not inside a Hydra job
        start = os.getcwd()
    rel = os.path.relpath(os.path.abspath(path), start)
    return os.path.abspath(path) if rel.startswith("..") else rel


def _one_line_warning(message, category, filename, lineno, line=None) -> str:
    """A warning as the commands print it: ``warning: <message>`` (the category unless it is the
    generic ``UserWarning``), without Python's file, line and echoed source."""
    kind = "" if category in (UserWarning, RuntimeWarning) else f" ({category.__name__})"
    return f"warning: {message}{kind}"


@contextlib.contextmanager
def command_warnings_and_logs():
    """For one job: warnings go to the log (terminal and run.log) as one line each; a log handler
    that cannot write (run.log on a full disk) is skipped quietly instead of printing a traceback
    per message (the results writer names the full disk itself)."""
    saved = warnings.formatwarning, logging.raiseExceptions
    warnings.formatwarning, logging.raiseExceptions = _one_line_warning, False
    logging.captureWarnings(True)
    try:
        yield
    finally:
        logging.captureWarnings(False)
        warnings.formatwarning, logging.raiseExceptions = saved


def hydra_entry(command: Command) -> Callable[[], None]:
    """The Hydra-decorated entry of ``command``: runs one job (every job of a sweep); a sweep (``-m``)
    goes on after a failing job, a stop request ends it: in the process of :func:`main` (Hydra's
    sequential launcher) at once; in a launcher's worker (joblib) the job returns, so that the launcher
    collects every job and no worker is killed while it writes, and the worker starts no further job
    (:func:`run_job`)."""

    def task(cfg: DictConfig) -> None:
        install_stop_handlers()  # again in a launcher's worker process (idempotent)
        with command_warnings_and_logs():
            code = _job(command, cfg)
        if multirun() and (code < 128 or os.getpid() != _MAIN_PID[0]):
            return  # the sweep goes on (or its workers wind down); the job's folder says what happened
        if code:
            sys.exit(code)

    task.__name__ = task.__qualname__ = f"{command.config_name}_task"
    return hydra.main(config_path=rc.config_source(), config_name=command.config_name, version_base="1.3")(task)


HELP_FLAGS = ("-h", "--help", "--hydra-help", "--info", "-c", "--cfg", "--version", "--shell-completion", "-sc")
#: the process id of :func:`main` (a launcher's worker process has another)
_MAIN_PID: List[Optional[int]] = [None]


def _one_line(text: str) -> str:
    return " ".join(ln.strip() for ln in str(text).splitlines() if ln.strip())


def _causes(e: BaseException):
    while e is not None:
        yield e
        e = e.__cause__ or e.__context__


#: a full disk or a folder that cannot be written, where Hydra writes (``.hydra/``, the log)
_WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM}


def hydra_error(e: Exception, command: Command, argv: Sequence[str]) -> tuple:
    """``(one-line message, exit status)`` of an error Hydra raised itself, or ``(None, 1)``: an override it
    cannot read (2: :func:`~torchflow.app.runner.config.unreadable_override_message`), of a key the config
    does not have (2: :func:`~torchflow.app.runner.config.unknown_override_messages`), any other composition
    error (2), a write into the output folder that failed (1: a full disk)."""
    from hydra.errors import ConfigCompositionException, OverrideParseException

    if isinstance(e, OverrideParseException):
        return rc.unreadable_override_message(argv) or _one_line(e), EXIT_CONFIG
    if isinstance(e, ConfigCompositionException):
        key = rc.missing_override_key(str(e))
        return "; ".join(rc.unknown_override_messages(command.config_name, argv, key)) if key else _one_line(
            e
        ), EXIT_CONFIG
    bad = next((x for x in _causes(e) if isinstance(x, OSError) and x.errno in _WRITE_ERRNOS), None)
    if bad is not None:
        key = "hydra.sweep.dir" if "hydra.sweep.dir" in GUARDED else "hydra.run.dir"
        where = bad.filename or GUARDED.get(key) or "the output folder"
        return (
            f"cannot write into {where} ({type(bad).__name__}: {bad.strerror or bad}); free space there or "
            f"choose another folder ({key}=<folder>)"
        ), EXIT_FAILED
    return None, EXIT_FAILED


@contextlib.contextmanager
def _hydra_errors_raised():
    """Hydra raises its own errors (``HYDRA_FULL_ERROR=1``) instead of printing them, so that
    :func:`main` says them in one line; yields whether the user asked for full errors anyway."""
    before = os.environ.get("HYDRA_FULL_ERROR")
    os.environ["HYDRA_FULL_ERROR"] = "1"
    try:
        yield before not in (None, "", "0")
    finally:
        if before is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = before


def _end_of_stopped_sweep(command: Command) -> None:
    """After a sweep a stop request ended (any launcher): the report of its jobs and, where chunks were
    saved, the command that goes on."""
    from torchflow.app.runner.sweep import report_sweep

    report_sweep(Path(GUARDED["hydra.sweep.dir"]), stopped_by=STOP.name)
    if command.resumable and GUARDED.get("checkpoint_dir") is not None:
        print(
            f"stopped by {STOP.name}; the finished chunks are saved: go on with\n  {rc.resume_command()}",
            file=sys.stderr,
        )
    else:
        print(f"stopped by {STOP.name}", file=sys.stderr)


def main(
    command: Command,
    argv: Optional[List[str]] = None,
    prog: Optional[str] = None,
    entry: Optional[Callable[[], None]] = None,
) -> None:
    """Start ``command`` with ``argv`` (default ``sys.argv[1:]``; Hydra overrides): refuse unknown
    config names in group selections (one line, exit 2), set the stop handlers, run Hydra (``entry``:
    the command's :func:`hydra_entry`), say Hydra's own errors in one line (:func:`hydra_error`), end a
    stopped sweep with its report, release the output folder's lock; exits with the job's status.
    ``prog``: the command in messages (default: the script as invoked,
    :func:`~torchflow.app.runner.config.invoked_as`)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    prog = prog or rc.invoked_as(sys.argv[0], command.prog)
    rank = os.environ.get("RANK", "0") if command.distributed else "0"
    try:
        rc.check_selections(argv)
        rc.remember_command(prog, argv)
        argv = rc.inline_configs(argv)  # model={_target_: ...}: the user's whole model, not merged into the default
        if int(rank) and any(a in ("-m", "--multirun") for a in argv):
            raise ConfigError("torchrun runs one job; run a sweep (-m) on a Hydra launcher instead")
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(EXIT_CONFIG)
    if int(rank):  # ranks other than 0 of a torchrun run write no Hydra folder or log (rank 0 does)
        argv += [
            f"hydra.run.dir={tempfile.gettempdir()}/torchflow-rank{rank}-{os.getppid()}",
            "hydra.output_subdir=null",
            "hydra/job_logging=disabled",
            "hydra/hydra_logging=disabled",
        ]
    STOP.reset()
    install_stop_handlers()
    GUARDED.clear()
    _MAIN_PID[0] = os.getpid()
    sys.argv = [sys.argv[0], *argv]
    code = EXIT_OK
    try:
        with _hydra_errors_raised() as full_errors:
            (entry or hydra_entry(command))()
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (EXIT_OK if e.code is None else EXIT_FAILED)
    except Exception as e:
        message, code = hydra_error(e, command, argv)
        if message is None and full_errors:
            raise
        print(f"error: {message}" if message else traceback.format_exc().rstrip(), file=sys.stderr)
    finally:
        release_locks()
    if STOP.requested and "hydra.sweep.dir" in GUARDED:
        _end_of_stopped_sweep(command)
        code = STOP.exit_code
    if code:
        sys.exit(code)


register_configs()  # the signature nodes the component configs extend (at import: sweep workers compose too)
# cached: a launcher that resolves the sweep folder again in each worker (joblib, submitit) gets
# the main process's value, so every job lands in the one announced folder
OmegaConf.register_new_resolver("tf_pid", lambda: str(os.getpid()), replace=True, use_cache=True)

__all__ = [
    "Command",
    "GUARDED",
    "JobEnv",
    "LOCK_NAME",
    "Output",
    "OutputGuard",
    "OutputLock",
    "config_error",
    "earlier_jobs",
    "earlier_results",
    "guard_output_folder",
    "hydra_entry",
    "hydra_error",
    "install_stop_handlers",
    "job_environment",
    "job_threads",
    "main",
    "release_locks",
    "run_job",
    "torch_threads",
]
