"""Bad input and faults around the run command: keys Hydra refuses, values its grammar cannot read,
selections, output folders (quoted, full), resuming, sweeps (overwrite, a stop on joblib) and
``collect.py``. Each fault gets one line that names what is wrong (exit status 2 for a setting) or a
warning, and nothing half done on disk. Subprocess runs are tiny (a few seconds each)."""

import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from torchflow.app.runner import ConfigError, shell
from torchflow.app.runner.config import check_selections, invoked_as, unknown_key_message

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "experiments" / "run.py"
TINY = ["model=linear_gaussian", "model.d=4", "trials=2", "steps=3", "n_particles=20", "progress=false", "plots=false"]


def _env():
    return dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")


def _run(cwd, *args, script=RUN):
    return subprocess.run(
        [sys.executable, str(script), *args], capture_output=True, text=True, cwd=cwd, timeout=180, env=_env()
    )


def _lines(text):
    return [ln for ln in text.splitlines() if ln.strip()]


# ----------------------------------------------------------------------------------------------
# settings Hydra refuses or cannot read


@pytest.mark.parametrize(
    "override, message",
    [
        ("n_particle=7", "error: n_particle: unknown setting; did you mean n_particles?"),
        ("filter.bpf.typo=1", "error: filter.bpf.typo: unknown setting; the settings of filter.bpf are n_particles, "),
        (
            "filter.bfp.n_particles=10",
            "error: filter.bfp.n_particles: expected one of the selected filters kf, bpf, got "
            "bfp; did you mean filter.bpf.n_particles?",
        ),
    ],
    ids=["misspelt-key", "unknown-filter-setting", "misspelt-filter"],
)
def test_a_key_the_config_lacks_given_without_plus_gets_did_you_mean_and_exit_2(tmp_path, override, message):
    r = _run(tmp_path, *TINY, "filter=[kf,bpf]", override, "hydra.run.dir=out")
    assert r.returncode == 2, r.stderr[-2000:]
    lines = _lines(r.stderr)
    assert len(lines) == 1 and lines[0].startswith(message), lines
    assert "+" not in lines[0] and "Traceback" not in r.stderr  # no hint to append the misspelt key
    assert list(tmp_path.iterdir()) == []


def test_a_setting_of_a_filter_that_is_not_selected_says_to_select_it():
    tree = {"trials": 2, "filter": {"kf": {"_target_": "x"}, "bpf": {"_target_": "y", "n_particles": 5}}}
    assert unknown_key_message(tree, "filter.ukf.alpha") == (
        "filter.ukf.alpha: expected one of the selected filters kf, bpf, got ukf (not selected; to set it, select it "
        "too: filter=[kf,bpf,ukf])"
    )
    assert unknown_key_message(tree, "trails") == "trails: unknown setting; did you mean trials?"
    assert unknown_key_message(None, "trails") == "trails: unknown setting"


@pytest.mark.parametrize(
    "override, hint",
    [
        ("hydra.run.dir=ünï码", "\"hydra.run.dir='ünï码'\""),
        ("label=ünï码 ☃/sub dir", "\"label='ünï码 ☃/sub dir'\""),
    ],
    ids=["folder", "label"],
)
def test_an_unquoted_non_ascii_value_gets_a_quoting_hint_and_exit_2(tmp_path, override, hint):
    r = _run(tmp_path, *TINY, "filter=[kf]", override)
    assert r.returncode == 2, r.stderr[-2000:]
    lines = _lines(r.stderr)
    key, value = override.split("=", 1)
    assert len(lines) == 1 and lines[0].startswith(f"error: {key}: expected a value Hydra can read unquoted"), lines
    assert f"got {value!r}" in lines[0] and lines[0].endswith(f"quote it for Hydra inside the shell's quotes: {hint}")
    assert list(tmp_path.iterdir()) == []  # no folder made before the refusal


def test_a_hydra_quoted_folder_with_spaces_and_non_ascii_is_written_as_named_and_guarded(tmp_path):
    folder = tmp_path / "dir with spaces" / "uni ünï码"
    quoted = "hydra.run.dir='dir with spaces/uni ünï码'"
    first = _run(tmp_path, *TINY, "filter=[kf]", "checkpoint_dir=null", quoted)
    assert first.returncode == 0, first.stderr[-2000:]
    assert (folder / "summary.csv").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["dir with spaces"]
    before = (folder / "results.json").read_text()
    again = _run(tmp_path, *TINY, "filter=[kf]", "checkpoint_dir=null", "seed=1", quoted)
    assert again.returncode == 2 and _lines(again.stderr) == [
        "error: hydra.run.dir: dir with spaces/uni ünï码 already holds the results of a run (summary.csv, "
        "per_step.csv, per_trial.csv, results.json); choose a new folder (hydra.run.dir=<new folder>) or add "
        "overwrite=true to replace them"
    ]
    assert (folder / "results.json").read_text() == before


def test_the_results_line_names_the_folder_from_where_the_command_started_also_with_chdir(tmp_path):
    """Hydra's ``hydra.job.chdir=true`` moves the job into its output folder: the results line still
    names that folder as seen from where the command was started (it used to print ``.``)."""
    done = _run(tmp_path, *TINY, "filter=[kf]", "checkpoint_dir=null", "hydra.job.chdir=true", "hydra.run.dir=out/a")
    assert done.returncode == 0, done.stderr[-2000:]
    assert "results: " + os.path.join("out", "a") in done.stdout + done.stderr
    assert (tmp_path / "out" / "a" / "summary.csv").exists()


def test_a_filter_selected_twice_is_refused_in_one_line_with_exit_2(capsys):
    from torchflow.app.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["model=linear_gaussian", "filter=[bpf,kf,bpf]", "trials=4"])
    assert stop.value.code == 2
    assert _lines(capsys.readouterr().err) == [
        "error: filter: expected each filter config once, got bpf 2 times in [bpf,kf,bpf] (one row per config); "
        "select it once, and to compare settings of one filter, sweep them: -m filter.bpf.<key>=a,b"
    ]


def test_a_sweep_over_lists_of_filters_is_not_refused():
    check_selections(["-m", "filter=[kf],[bpf,ekf]"])
    with pytest.raises(ConfigError, match=r"filter: unknown filter config 'bfp'"):
        check_selections(["-m", "filter=[kf],[bfp]"])
    with pytest.raises(ConfigError, match=r"got kf 2 times in \[kf,kf\]"):
        check_selections(["-m", "filter=[bpf],[kf,kf]"])


@pytest.mark.parametrize(
    "trials, inits_per_track, warning, groups",
    [
        (
            4,
            3,
            "inits_per_track=3 does not divide trials=4: the last trajectory is shared by 1 trial, the others by 3 "
            "(trials=6 keeps the groups equal)",
            [3, 1],
        ),
        (4, 10, "inits_per_track=10 is more than trials=4: all 4 trials share one trajectory", [4]),
        (6, 3, None, [3, 3]),
    ],
)
def test_inits_per_track_that_leaves_unequal_groups_of_trials_warns(trials, inits_per_track, warning, groups):
    import warnings

    import torch

    from torchflow.app.runner.execute import plan_run
    from torchflow.models import SensorNetwork

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        plan = plan_run(SensorNetwork(d=4), {}, trials=trials, steps=2, seed=0, inits_per_track=inits_per_track)
    said = [str(w.message) for w in seen if "inits_per_track" in str(w.message)]
    assert said == [] if warning is None else (len(said) == 1 and said[0].startswith(warning)), said
    states = plan.traj.states  # the groups the warning describes are the trials that share a trajectory
    sizes, start = [], 0
    while start < trials:
        same = [torch.equal(states[start], states[i]) for i in range(start, trials)]
        sizes.append(same.index(False) if False in same else len(same))
        start += sizes[-1]
    assert sizes == groups


# ----------------------------------------------------------------------------------------------
# output folders and checkpoints


_FULL_DISK = """import errno
import hydra.core.utils


def full(cfg, filename, output_dir):
    raise OSError(errno.ENOSPC, "No space left on device")


hydra.core.utils._save_config = full  # where Hydra writes .hydra/config.yaml
from torchflow.app.cli import main
main()
"""


def test_a_full_disk_while_hydra_writes_its_config_is_one_line_naming_the_folder(tmp_path):
    (tmp_path / "full_disk.py").write_text(_FULL_DISK)
    r = _run(tmp_path, *TINY, "filter=[kf]", "checkpoint_dir=null", "hydra.run.dir=out", script="full_disk.py")
    assert r.returncode == 1, r.stderr[-2000:]
    assert _lines(r.stderr) == [
        f"error: cannot write into {tmp_path / 'out'} (OSError: No space left on device); "
        "free space there or choose another folder (hydra.run.dir=<folder>)"
    ]
    assert not (tmp_path / "out" / shell.LOCK_NAME).exists()


def test_resume_with_nothing_saved_says_so_and_computes_every_chunk(tmp_path, caplog):
    import torch
    from hydra import compose, initialize_config_dir

    from torchflow.app.cli import chunk_store

    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        cfg = compose(
            "config", ["model=linear_gaussian", "filter=[kf,bpf]", "resume=true", f"checkpoint_dir={tmp_path / 'ck'}"]
        )
    labels = {"kf": "kf", "bpf": "bpf"}
    with caplog.at_level(logging.WARNING, logger="torchflow.app.cli"):
        store = chunk_store(cfg, labels)
    assert [r.getMessage() for r in caplog.records] == [
        f"resume=true: nothing is saved under {tmp_path / 'ck'} with these settings (a new folder, or settings other "
        "than the saved run's, which save under another key): every chunk is computed"
    ]
    store.save("kf", 0, 2, {"estimates": torch.zeros(2, 3, 4)})
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="torchflow.app.cli"):
        chunk_store(cfg, labels)
    assert [r.getMessage() for r in caplog.records] == [
        f"resume=true: nothing is saved under {tmp_path / 'ck'} for bpf with these settings: their chunks are computed"
    ]
    caplog.clear()
    cfg.resume = False
    with caplog.at_level(logging.WARNING, logger="torchflow.app.cli"):
        chunk_store(cfg, labels)
    assert caplog.records == []  # not resuming: nothing to say


def test_two_live_runs_sharing_a_checkpoint_dir_keep_their_chunks_apart(tmp_path):
    """Runs of other settings (here seeds) save under other keys; the same settings save the same chunks
    (written atomically), so a shared checkpoint_dir needs no lock (trial_range runs share one)."""

    def cmd(seed):
        return [
            sys.executable,
            str(RUN),
            *TINY,
            "filter=[kf]",
            f"seed={seed}",
            "checkpoint_dir=ck",
            f"hydra.run.dir=run{seed}",
        ]

    procs = [
        subprocess.Popen(
            cmd(seed), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=tmp_path, env=_env()
        )
        for seed in (0, 1)
    ]
    errs = [p.communicate(timeout=180)[1] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], errs
    saved = sorted(json.loads(f.read_text())["seed"] for f in (tmp_path / "ck").glob("kf-*/settings.json"))
    assert saved == [0, 1]
    assert all(len(list(d.glob("*.pt"))) == 1 for d in (tmp_path / "ck").glob("kf-*"))


def test_the_resume_hint_repeats_the_script_as_invoked_from_another_folder(tmp_path):
    work = tmp_path / "w"
    work.mkdir()
    script = os.path.relpath(RUN, work)  # python ../../<...>/experiments/run.py
    cmd = [
        sys.executable,
        script,
        "model=linear_gaussian",
        "filter=[bpf]",
        "trials=40",
        "steps=50",
        "n_particles=20000",
        "chunk_size=1",
        "progress=false",
        "plots=false",
        "checkpoint_dir=ck",
        "hydra.run.dir=run",
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=work, env=_env())
    deadline = time.time() + 120
    while not list((work / "ck").glob("*/*.pt")) and time.time() < deadline and proc.poll() is None:
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    err = proc.communicate(timeout=120)[1]
    assert proc.returncode == 130, err[-2000:]
    lines = _lines(err)
    hint = lines[lines.index(next(ln for ln in lines if ln.endswith("go on with"))) + 1].strip()
    assert hint.startswith(f"python {script} model=linear_gaussian") and hint.endswith("hydra.run.dir=run resume=true")
    assert (work / script).exists()  # the hint works from that folder


def test_invoked_as_repeats_a_script_and_names_an_entry_point():
    assert invoked_as("../experiments/run.py", "torchflow") == "python ../experiments/run.py"
    assert invoked_as("/my repo/experiments/run.py", "torchflow") == "python '/my repo/experiments/run.py'"
    assert invoked_as("/venv/bin/torchflow", "torchflow") == "torchflow"
    assert invoked_as("/x/torchflow/__main__.py", "torchflow") == "torchflow"


# ----------------------------------------------------------------------------------------------
# sweeps and collect


def _job(sweep, name, seed, results=True, text=None):
    job = sweep / name
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([f"seed={seed}"]))
    (job / "summary.csv").write_text("filter,trials,mse,error\nkf,2,0.5,\n")
    (job / "per_trial.csv").write_text("filter,trial,mse\nkf,0,0.4\nkf,1,0.6\n")
    if results:
        (job / "results.json").write_text(text or json.dumps({"summary": [{"filter": "kf", "error": None}]}))
    return job


def test_a_sweep_folder_holding_an_earlier_sweeps_jobs_is_refused_or_replaced(tmp_path):
    failed = tmp_path / "0"
    (failed / ".hydra").mkdir(parents=True)
    (failed / "error.txt").write_text("error: bad\n")
    (tmp_path / "1" / ".hydra").mkdir(parents=True)  # killed before it wrote anything
    (tmp_path / "7").mkdir()  # not a job's folder
    assert shell.earlier_results(tmp_path, sweep=True) == ["0/error.txt", "1/"]
    with pytest.raises(
        ConfigError,
        match=r"hydra.sweep.dir: .* already holds the jobs of an earlier sweep "
        r"\(0/error.txt, 1/\); choose a new folder",
    ):
        shell.guard_output_folder(tmp_path, key="hydra.sweep.dir", sweep=True)
    shell.guard_output_folder(tmp_path, sweep=True, replace=True).release()  # resume=true: the same jobs again
    assert failed.exists()
    (tmp_path / "sweep_summary.csv").write_text("job\n")
    overwrite = shell.guard_output_folder(tmp_path, sweep=True, replace=True, clear_jobs=True)  # overwrite=true
    overwrite.release()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["7"]


def test_overwrite_true_on_a_sweep_folder_reports_and_collects_only_the_new_jobs(tmp_path):
    from experiments.collect import collect

    sweep = tmp_path / "sw2"
    for n in range(3):
        _job(sweep, str(n), seed=n)
    r = _run(
        tmp_path, "-m", *TINY, "filter=[kf]", "checkpoint_dir=null", "seed=5,6", "overwrite=true", "hydra.sweep.dir=sw2"
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert "sweep sw2: 2 jobs, 2 finished, 0 failed" in r.stderr
    assert "warning: overwrite=true: removed 3 job folder(s) of an earlier sweep from sw2 (0, 1, 2)" in r.stderr
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0", "1"]
    rows, _, missing = collect(sweep)
    assert [(r["job"], r["seed"]) for r in rows] == [("0", "5"), ("1", "6")] and missing == []


def test_collect_names_a_damaged_results_json_and_merges_its_intact_csvs(tmp_path, capsys):
    from experiments.collect import collect, main
    from torchflow.app.runner.sweep import report_sweep

    sweep = tmp_path / "sw"
    damaged = _job(sweep, "0", seed=0, text=json.dumps({"summary": [{"filter": "kf", "error": None}]})[:20])
    _job(sweep, "1", seed=1)
    rows, _, missing = collect(sweep)
    assert [(r["job"], r["seed"], r["mse"]) for r in rows] == [("0", "0", "0.5"), ("1", "1", "0.5")]
    assert [m["state"] for m in missing] == ["damaged"]
    main([str(sweep)])
    out = capsys.readouterr().out
    note = next(ln for ln in out.splitlines() if ln.startswith("job 0"))
    assert note.startswith(f"job 0 (seed=0): {damaged / 'results.json'} is damaged (JSONDecodeError: ")
    assert "its summary.csv and per_trial.csv, written before it, are merged" in note
    assert "to write it again, rerun the job into its folder" in note
    assert report_sweep(sweep)["damaged"] == 1
    assert f"{damaged / 'results.json'} is damaged" in capsys.readouterr().err


@pytest.mark.slow  # 15 s; test_experiment's Ctrl-C of a single run stays in the default tier
def test_ctrl_c_to_a_joblib_sweep_ends_with_the_report_the_resume_command_and_exit_130(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    cmd = [
        sys.executable,
        str(RUN),
        "-m",
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2",
        "model=linear_gaussian",
        "filter=[bpf]",
        "trials=40",
        "steps=50",
        "n_particles=20000",
        "chunk_size=1",
        "progress=false",
        "plots=false",
        "seed=0,1,2",
        "checkpoint_dir=ck",
        "hydra.sweep.dir=sw",
    ]
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
        env=_env(),
        start_new_session=True,
    )  # its own process group, as a terminal's
    deadline = time.time() + 180
    while len(list((tmp_path / "ck").glob("*/*.pt"))) < 2 and time.time() < deadline and proc.poll() is None:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C: every process of the group
    err = proc.communicate(timeout=180)[1]
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in err and "KeyboardInterrupt" not in err and "leaked" not in err, err[-3000:]
    lines = _lines(err)
    assert any(
        ln.startswith(f"sweep {tmp_path / 'sw'} (stopped by Ctrl-C): 3 jobs, 0 finished, 0 failed, 2 interrupted")
        for ln in lines
    ), lines
    assert lines[-2] == "stopped by Ctrl-C; the finished chunks are saved: go on with"
    assert lines[-1].strip().startswith(f"python {RUN} -m hydra/launcher=joblib")
    assert lines[-1].endswith(" resume=true")
    for job in ("0", "1"):  # no worker was killed while it wrote its files
        assert json.loads((tmp_path / "sw" / job / "results.json").read_text())["interrupted"] is True
        assert (tmp_path / "sw" / job / "per_trial.csv").exists()


def test_a_log_file_that_cannot_be_written_does_not_print_a_traceback_per_message(capsys):
    """run.log on a full disk: the handler's failure is skipped quietly inside a command's job
    (the results writer names the full disk in one line), and warnings print as one line each."""

    class FullDisk(logging.Handler):
        def emit(self, record):
            try:
                raise OSError(28, "No space left on device")
            except OSError:
                self.handleError(record)

    logger = logging.getLogger("torchflow.test_full_disk")
    handler = FullDisk()
    logger.addHandler(handler)
    try:
        with shell.command_warnings_and_logs():
            logger.error("a message while the disk is full")
            import warnings

            assert warnings.formatwarning("groups are unequal", UserWarning, "x.py", 1) == "warning: groups are unequal"
        assert "Logging error" not in capsys.readouterr().err
        assert logging.raiseExceptions  # restored after the job
        logger.error("outside a job, Python's default applies")
        assert "Logging error" in capsys.readouterr().err
    finally:
        logger.removeHandler(handler)


@pytest.mark.parametrize(
    "script, name, guide",
    [(RUN, "torchflow", "command-line.md"), (ROOT / "experiments" / "learn.py", "torchflow-learn", "learning.md")],
)
def test_help_says_what_the_command_does_with_examples_and_the_documentation(tmp_path, script, name, guide):
    """``--help`` is a page, not a config dump: what the command does, examples, where the guide
    is, the config groups, in at most 60 lines; nothing written to disk."""
    out = _run(tmp_path, "--help", script=script)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert len(lines) <= 60, len(lines)
    assert lines[0].startswith(f"{name}: "), lines[0]
    assert "Examples:" in out.stdout and f"\n  {name}" in out.stdout
    assert f"docs/guide/{guide}" in out.stdout
    assert "\nfilter: " in out.stdout and "\nmodel: " in out.stdout  # the groups are listed
    assert "_target_: torchflow." not in out.stdout  # and the composed config is not
    assert list(tmp_path.iterdir()) == []


def test_a_sweep_of_tasks_counts_its_finished_jobs_and_collect_says_what_it_merges(tmp_path, capsys):
    """Cases C01, C02: sweeps of task=smooth / task=pmmh reported "0 finished ... 2 without results"
    although both jobs wrote their results, and collect.py said no job had results yet."""
    from experiments.collect import main
    from torchflow.app.runner.sweep import job_status, report_sweep

    sweep = tmp_path / "sw"
    for name, seed, file, content in (
        ("0", 0, "smoothing.json", {"summary": [{"filter": "kf"}]}),
        ("1", 1, "pmmh.json", {"run": {"interrupted": None}, "filters": {}}),
        ("2", 2, "pmmh.json", {"run": {"interrupted": "bpf"}, "filters": {}}),
    ):
        job = sweep / name
        (job / ".hydra").mkdir(parents=True)
        (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([f"seed={seed}"]))
        (job / file).write_text(json.dumps(content))
    assert [job_status(sweep / n)[0] for n in "012"] == ["done", "done", "interrupted"]
    counts = report_sweep(sweep)
    assert "3 jobs, 2 finished, 0 failed, 1 interrupted, 0 without results" in capsys.readouterr().err
    assert counts["missing"] == 0
    with pytest.raises(SystemExit) as stop:
        main([str(sweep)])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "ran a task (their results are pmmh.json, smoothing.json in each job folder)" in err
    # Q75: a sweep mixing task=filter and task=smooth: the run's table is merged, the smoothing job is
    # named as such, not as a job 'without results (still running, killed, or never started)'
    mixed = tmp_path / "mixed"
    for name, task in (("0", "filter"), ("1", "smooth")):
        job = mixed / name
        (job / ".hydra").mkdir(parents=True)
        (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([f"task={task}"]))
    (mixed / "0" / "summary.csv").write_text("filter,rmse\nkf,0.5\n")
    (mixed / "0" / "results.json").write_text(json.dumps({"summary": [{"filter": "kf"}]}))
    (mixed / "1" / "smoothing.json").write_text(json.dumps({"summary": [{"filter": "kf"}]}))
    main([str(mixed)])
    out = capsys.readouterr().out
    assert "| 0 | kf |" in out
    assert "job 1 (task=smooth) ran a task: its results are smoothing.json in its folder" in out
    assert "without results" not in out and "has no results" not in out


def test_a_constructor_s_message_keeps_its_own_closing_quote():
    """Q34: ``got '.inf'`` lost its closing quote (both ends were stripped of quotes whatever they
    held); only a message quoted whole (a KeyError's) loses its quotes."""
    from hydra.errors import InstantiationException

    def wrapped(cause):
        try:
            try:
                raise cause
            except Exception as c:
                raise InstantiationException("Error in call\nfull_key: filter.lpf") from c
        except InstantiationException as e:
            return shell.config_error(e)

    got = wrapped(ValueError("radius: expected a number > 0, got '.inf'"))
    assert got == "filter.lpf: radius: expected a number > 0, got '.inf'"
    assert wrapped(TypeError("'learnable'")) == "filter.lpf: learnable"
