"""Nothing is written through a link planted in a shared folder (cases SEC1, SEC2, Q125, Q126): temporary files
are created exclusively under random names, and a chunk file that is a link is neither read nor
followed."""

import itertools
import os

import pytest
import torch

from torchflow.app.runner.checkpoint import ChunkStore
from torchflow.app.runner.shell import guard_output_folder
from torchflow.app.runner.writers import exclusive_temp, write_text


def _victim(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious user data")
    return victim


def test_a_result_file_is_not_written_through_a_link_at_the_old_temporary_name(tmp_path):
    victim, out = _victim(tmp_path), tmp_path / "out"
    out.mkdir()
    (out / f".summary.csv.{os.getpid()}.tmp").symlink_to(victim)  # the name the writers used to take
    write_text(out / "summary.csv", "a,b\n")
    assert victim.read_text() == "precious user data"
    assert (out / "summary.csv").read_text() == "a,b\n" and not (out / "summary.csv").is_symlink()


def test_exclusive_temporary_files_refuse_an_existing_entry(tmp_path, monkeypatch):
    """Even at a name an attacker guessed, the temporary file is not opened through a link: the
    exclusive open fails (mkstemp then tries other names, here all the same one, and gives up)."""
    import tempfile

    victim, out = _victim(tmp_path), tmp_path / "out"
    out.mkdir()
    (out / ".summary.csv.fixed.tmp").symlink_to(victim)
    monkeypatch.setattr(tempfile, "_get_candidate_names", lambda: itertools.repeat("fixed"))
    monkeypatch.setattr(tempfile, "TMP_MAX", 5)
    with pytest.raises(FileExistsError):
        exclusive_temp(out / "summary.csv")
    assert victim.read_text() == "precious user data"


def test_a_chunk_is_not_saved_through_a_link_nor_a_linked_chunk_loaded(tmp_path):
    victim, root = _victim(tmp_path), tmp_path / "ck"
    store = ChunkStore(root, {"bpf": "bpf-key"}, resume=True)
    folder = store.folder("bpf")
    folder.mkdir(parents=True)
    (folder / f".0000000-0000002.pt.{os.getpid()}.tmp").symlink_to(victim)  # case SEC1's planted link
    chunk = {"estimates": torch.zeros(2, 3, 1, dtype=torch.float64)}
    path = store.save("bpf", 0, 2, chunk)
    assert victim.read_text() == "precious user data" and not path.is_symlink()
    assert store.load("bpf", 0, 2, steps=3) is not None  # the store's own file reads back
    # a link planted at the chunk's own name (to a chunk elsewhere) is refused, with a warning
    elsewhere = tmp_path / "elsewhere.pt"
    os.replace(path, elsewhere)
    path.symlink_to(elsewhere)
    with pytest.warns(UserWarning, match="is not a regular file"):
        assert store.load("bpf", 0, 2, steps=3) is None
    store.save("bpf", 0, 2, chunk)  # saving replaces the link itself, not its target
    assert not path.is_symlink() and elsewhere.exists()


def test_the_output_folder_probe_does_not_truncate_a_linked_file(tmp_path):
    victim, out = _victim(tmp_path), tmp_path / "run"
    out.mkdir()
    (out / f".torchflow-write-test.{os.getpid()}").symlink_to(victim)  # case SEC2
    lock = guard_output_folder(out, key="hydra.run.dir", command="torchflow")
    try:
        assert victim.read_text() == "precious user data"
    finally:
        lock.release()


def test_a_chunk_with_non_finite_estimates_is_computed_again(tmp_path):
    """Case K06: a chunk rewritten with NaN estimates and a matching checksum resumed into NaN metrics
    with an empty error column; a run that computed NaN would have stopped with NonFiniteError."""
    import math

    from torchflow.app.runner.checkpoint import checksum

    store = ChunkStore(tmp_path / "ck", {"bpf": "bpf-key"}, resume=True)
    chunk = {
        "estimates": torch.zeros(2, 3, 1, dtype=torch.float64),
        "log_evidence": torch.zeros(2, dtype=torch.float64),
    }
    path = store.save("bpf", 0, 2, chunk)
    assert store.load("bpf", 0, 2, steps=3) is not None
    data = torch.load(path, weights_only=True)
    data["estimates"][1, 2, 0] = math.nan
    data["checksum"] = checksum(data)  # crafted to match
    torch.save(data, path)
    with pytest.warns(UserWarning, match="holds NaN or infinite estimates"):
        assert store.load("bpf", 0, 2, steps=3) is None
    data["estimates"][1, 2, 0] = 0.0
    data["log_evidence"][0] = -math.inf  # no weight carried the measurement: a finished run's -inf is kept
    data["checksum"] = checksum(data)
    torch.save(data, path)
    assert store.load("bpf", 0, 2, steps=3) is not None


def test_result_files_keep_the_mode_a_plain_open_gives(tmp_path):
    """The exclusive temporary file is created 0600; the result it becomes is 0644 less the umask,
    as before (others sharing the folder can still read the results)."""
    from torchflow.app.runner import writers

    path = write_text(tmp_path / "summary.csv", "a\n")
    assert path.stat().st_mode & 0o777 == 0o644 & ~writers._UMASK


@pytest.mark.parametrize("name", ["run.log", ".hydra/overrides.yaml", ".hydra/config.yaml", ".hydra", "multirun.yaml"])
def test_a_folder_with_a_link_where_hydra_or_the_log_write_is_refused(tmp_path, name):
    """Q125, Q126: Hydra writes ``.hydra/*.yaml`` and the log with a plain ``open``, before the job,
    so a link planted at one of those names (or at ``.hydra`` itself) is refused by the output
    guard in one line naming it, and its target is left untouched."""
    from torchflow.app.runner.plan import ConfigError

    victim, out = _victim(tmp_path), tmp_path / "run"
    (out / name).parent.mkdir(parents=True, exist_ok=True)
    (out / name).symlink_to(victim if name != ".hydra" else tmp_path)
    with pytest.raises(ConfigError, match=rf"hydra.run.dir: .* holds links at names a run writes itself \({name} -> "):
        guard_output_folder(out, key="hydra.run.dir", command="torchflow")
    assert victim.read_text() == "precious user data"
    assert not (out / ".torchflow.lock").exists()


def test_a_sweep_folder_with_a_link_in_a_job_folder_or_as_a_job_folder_is_refused(tmp_path):
    from torchflow.app.runner.plan import ConfigError

    victim, sweep = _victim(tmp_path), tmp_path / "sw"
    (sweep / "0" / ".hydra").mkdir(parents=True)
    (sweep / "0" / ".hydra" / "hydra.yaml").symlink_to(victim)
    (sweep / "1").symlink_to(tmp_path)
    with pytest.raises(ConfigError, match=r"0/.hydra/hydra.yaml -> .*, 1 -> "):
        guard_output_folder(sweep, key="hydra.sweep.dir", sweep=True, replace=True, command="torchflow")
    assert victim.read_text() == "precious user data"


def test_the_run_log_is_not_appended_through_a_link_planted_after_the_check(tmp_path):
    """The log handler opens ``run.log`` with ``O_NOFOLLOW``: a link planted between the guard's
    check and the open makes the open fail rather than append to the target; a plain file is
    appended to as :class:`logging.FileHandler` does."""
    import logging

    from torchflow.app.runner.logs import NoFollowFileHandler

    victim = _victim(tmp_path)
    (tmp_path / "run.log").symlink_to(victim)
    with pytest.raises(OSError):
        NoFollowFileHandler(str(tmp_path / "run.log"))
    assert victim.read_text() == "precious user data"
    handler = NoFollowFileHandler(str(tmp_path / "plain.log"))
    handler.emit(logging.LogRecord("t", logging.INFO, "x", 1, "first", None, None))
    handler.close()
    handler = NoFollowFileHandler(str(tmp_path / "plain.log"))
    handler.emit(logging.LogRecord("t", logging.INFO, "x", 1, "second", None, None))
    handler.close()
    assert (tmp_path / "plain.log").read_text() == "first\nsecond\n"


def test_a_run_into_a_folder_with_a_linked_run_log_is_refused_end_to_end(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    victim, out = _victim(tmp_path), tmp_path / "run"
    out.mkdir()
    (out / "run.log").symlink_to(victim)
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(root), OMP_NUM_THREADS="1")
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "torchflow",
            "model=linear_gaussian",
            "filter=[kf]",
            "trials=1",
            "steps=2",
            "plots=false",
            "progress=false",
            "checkpoint_dir=null",
            f"hydra.run.dir={out}",
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=env,
        timeout=120,
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert r.stderr.strip().splitlines()[-1].startswith("error: hydra.run.dir: ")
    assert victim.read_text() == "precious user data"


def test_a_hydra_folder_another_user_owns_is_refused(tmp_path, monkeypatch):
    """Another user who owns ``.hydra`` could put links into it after the guard's check, before
    Hydra writes its files: such a folder is refused, naming it (here the folder is made to look
    foreign by a different user id)."""
    from torchflow.app.runner.plan import ConfigError

    out = tmp_path / "run"
    (out / ".hydra").mkdir(parents=True)
    guard_output_folder(out, key="hydra.run.dir", command="torchflow").release()  # our own: accepted
    monkeypatch.setattr(os, "getuid", lambda: os.stat(out / ".hydra").st_uid + 1)
    with pytest.raises(ConfigError, match=r"holds links at names a run writes itself \(.hydra \(another user's\)"):
        guard_output_folder(out, key="hydra.run.dir", command="torchflow")
