"""Property-based fuzz of recorded files, per-trial values and the task settings. Each example
either gives the right result (the values written, a finite filter result) or raises torchflow's
own error naming what was wrong; never a raw error, never a silent change of the data.

Examples are drawn as in ``tests/test_fuzz_validation.py`` (``derandomize=True``: CI draws the
same ones; ``TORCHFLOW_FUZZ_EXAMPLES=3000`` fuzzes deeper with fresh examples).
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import event, given
from hypothesis import strategies as st
from test_fuzz_validation import fuzz

from torchflow.app.data import load_observations
from torchflow.core.errors import TorchflowError
from torchflow.filters import BootstrapParticleFilter, KalmanFilter
from torchflow.inference.params import per_trial_values
from torchflow.models import LinearGaussian, StochasticVolatility

ROOT = Path(__file__).resolve().parents[1]
F64 = torch.float64
M = 2  # the measurement dimension of the model the files are read for


def _model(m: int = M) -> LinearGaussian:
    eye = torch.eye(m, dtype=F64)
    return LinearGaussian(0.9 * eye, 0.2 * eye, eye, 0.1 * eye, torch.zeros(m, dtype=F64), eye)


# ----------------------------------------------------------------------------------------------
# recorded CSV files

#: plants a reader must accept without changing the values (comments, blank lines, spaces, CRLF)
BENIGN = ("comment", "blank", "spaces", "crlf", "no_final_newline")
#: plants that must be refused, each with a word its message must hold
REFUSED = {
    "word": "numbers",
    "inf": "finite",
    "huge": "overflow",
    "ragged": "columns in every row",
    "semicolons": "comma-separated",
    "extra_column": "measurement coordinates",
    "all_nan": "no observation",
    "uneven_time": "uniform time step",
    "backward_time": "increase row by row",
    "nan_time": "finite observation times",
    "header_with_number": "header of column names or a row of numbers",
    "header_only": "after the header",
    "empty": "empty file",
    "bytes": "not text",
}


@st.composite
def csv_files(draw):
    """``(text or bytes, values (T, M) with NaN, plants)``: a valid table of T rows, optionally a
    header and a uniform time column, with benign and refused plants."""
    T = draw(st.integers(1, 6))
    cell = st.one_of(
        st.floats(-1e6, 1e6, allow_nan=False, width=64),
        st.sampled_from([0.0, -0.0, 1e-300, 123456789.0]),
        st.just(math.nan),
    )
    values = np.array([[draw(cell) for _ in range(M)] for _ in range(T)], dtype=np.float64)
    if np.isnan(values).all():
        values[0, 0] = 1.0
    header, time = draw(st.booleans()), draw(st.booleans())
    plants = draw(st.lists(st.sampled_from(BENIGN + tuple(REFUSED)), max_size=2, unique=True))
    if not header:
        plants = [p for p in plants if p not in ("uneven_time", "backward_time", "nan_time", "header_only")]
        time = False
    if "header_with_number" in plants:
        header = True
    if any(p.endswith("_time") for p in plants):
        time = True
    if "all_nan" in plants:
        values[:] = math.nan

    def fmt(v):
        return draw(st.sampled_from(["", "nan", "NaN"])) if math.isnan(v) else repr(float(v))

    t0, dt = draw(st.sampled_from([0.0, 3.5, -2.0])), draw(st.sampled_from([0.1, 1.0, 0.05]))
    times = [t0 + k * dt for k in range(T)]
    if "uneven_time" in plants and T >= 3:
        times[-1] += 2.5 * dt
    elif "backward_time" in plants and T >= 2:
        times = times[::-1]
    elif "nan_time" in plants and T >= 2:
        times[-1] = math.nan
    else:
        plants = [p for p in plants if not p.endswith("_time")]
    rows = [[fmt(v) for v in r] for r in values]
    names = [f"z{j}" for j in range(M)]
    where = None  # the time column's index
    if time:
        where = draw(st.integers(0, M))
        names.insert(where, draw(st.sampled_from(["t", "time", "Time"])))
        for r, t in zip(rows, times):
            r.insert(where, repr(t))
    if "extra_column" in plants:
        names.append("z_extra")
        for r in rows:
            r.append("0.5")
    i = draw(st.integers(0, T - 1))
    if "word" in plants:
        rows[i][draw(st.integers(0, len(rows[i]) - 1))] = draw(st.sampled_from(["abc", "1.0e", "--", "0x1g"]))
    meas = [j for j in range(len(rows[i])) if j != where]  # the measurement columns
    if "inf" in plants:
        rows[i][draw(st.sampled_from(meas))] = draw(st.sampled_from(["inf", "-inf", "Infinity"]))
    if "huge" in plants:
        rows[i][draw(st.sampled_from(meas))] = draw(st.sampled_from(["1e200", "-3e160"]))
    if "ragged" in plants:
        rows[i].append("1.0")
    lines = []
    if header:
        head = list(names)
        if "header_with_number" in plants:
            head[-1] = "2.5"
        lines.append(",".join(head))
    lines += [",".join(r) for r in rows]
    if "header_only" in plants:
        lines = lines[:1]
    if "comment" in plants:
        lines.insert(
            draw(st.integers(0, len(lines))), "# recorded on the bench, " + draw(st.sampled_from(["a,b", "1,2", "x"]))
        )
    if "blank" in plants:
        lines.insert(draw(st.integers(0, len(lines))), draw(st.sampled_from(["", " ", "\t"])))
    if "spaces" in plants:
        lines = [", ".join(c.strip() for c in ln.split(",")) if not ln.startswith("#") else ln for ln in lines]
    if "semicolons" in plants:
        lines = [ln.replace(",", ";") for ln in lines]
    eol = "\r\n" if "crlf" in plants else "\n"
    text = eol.join(lines) + ("" if "no_final_newline" in plants else eol)
    if "empty" in plants:
        text = ""
    if "bytes" in plants:
        return bytes(range(256)) * 2, values, plants
    return text, values, plants


def _one_line_error(e: BaseException) -> str:
    assert isinstance(e, TorchflowError), f"a raw {type(e).__name__}: {e}"
    message = str(e)
    assert "\n" not in message and message.startswith("data"), message
    return message


@given(case=csv_files())
@fuzz(300)
def test_a_recorded_csv_file_is_read_exactly_or_refused_in_one_line(case):
    """A file with benign plants only is read back to exactly the values written (NaN where not
    observed); any refused plant gives one line naming ``data`` and the fault; a line number in
    the message is the line of the file that holds the fault."""
    content, values, plants = case
    refused = [p for p in plants if p in REFUSED]
    event(f"plants: {sorted(plants) or 'none'}")
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "series.csv"
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_bytes(content.encode())
        try:
            obs = load_observations(path, _model())
        except Exception as e:  # noqa: BLE001 - the property: torchflow's own one-line error
            message = _one_line_error(e)
            assert refused, f"refused a valid file ({plants}): {message}\n{content!r}"
            assert any(REFUSED[p] in message for p in refused), (plants, message)
            line = re.search(r"\bline (\d+)", message)
            if line and not isinstance(content, bytes):
                text_lines = content.replace("\r\n", "\n").split("\n")
                assert int(line.group(1)) <= len(text_lines)
                shown = text_lines[int(line.group(1)) - 1]
                assert shown.strip() and not shown.startswith("#"), (message, content)
            return
    assert not refused, f"accepted a file with {refused}:\n{content!r}"
    assert obs.shape == values.shape and obs.dtype == F64
    assert torch.equal(torch.isnan(obs), torch.from_numpy(np.isnan(values)))
    seen = ~torch.isnan(obs)
    assert torch.equal(obs[seen], torch.from_numpy(values)[seen])


@st.composite
def npy_arrays(draw):
    """``(array, expected (T, M) float64 or None: refused)``."""
    kind = draw(st.sampled_from(["good", "good3", "vector", "scalar", "4d", "wrong_m", "empty_T", "int", "float32"]))
    kind2 = draw(st.sampled_from(["", "bool", "complex", "object", "str", "inf", "all_nan"]))
    T = draw(st.integers(1, 5))
    base = np.arange(T * M, dtype=np.float64).reshape(T, M) / 7 - 1
    arr = {
        "good": base,
        "good3": np.stack([base, base + 1]),
        "vector": base[:, 0],
        "scalar": np.float64(1.5),
        "4d": base[None, None],
        "wrong_m": np.ones((T, M + 1)),
        "empty_T": np.ones((0, M)),
        "int": (base * 7).astype(np.int32),
        "float32": base.astype(np.float32),
    }[kind]
    ok = kind in ("good", "good3", "int", "float32")
    arr = np.array(arr)
    if kind2 == "bool":
        arr, ok = arr > 0, False
    elif kind2 == "complex":
        arr, ok = arr.astype(np.complex128), False
    elif kind2 == "object":
        arr, ok = arr.astype(object), False
    elif kind2 == "str":
        arr, ok = arr.astype(str), False
    elif kind2 in ("inf", "all_nan") and arr.size and arr.dtype.kind == "f":
        arr = arr.copy()
        if kind2 == "inf":
            arr.flat[draw(st.integers(0, arr.size - 1))] = np.inf
        else:
            arr[...] = np.nan
        ok = False
    event(f"{kind}/{kind2 or '-'}")
    return arr, (arr.astype(np.float64) if ok else None)


@given(case=npy_arrays())
@fuzz(120)
def test_a_recorded_npy_file_is_read_exactly_or_refused_in_one_line(case):
    """Numeric ``(T, m)`` / ``(B, T, m)`` arrays come back exactly as float64; every other array
    (another shape, m, dtype, an object array: never unpickled, infinities, no observation) is one
    line naming ``data``."""
    arr, expected = case
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "series.npy"
        np.save(path, arr, allow_pickle=True)
        try:
            obs = load_observations(path, _model())
        except Exception as e:  # noqa: BLE001
            _one_line_error(e)
            assert expected is None, f"refused a valid array {arr.dtype} {arr.shape}: {e}"
            return
    assert expected is not None, f"accepted {arr.dtype} {arr.shape}"
    assert torch.equal(obs, torch.from_numpy(expected))


# ----------------------------------------------------------------------------------------------
# per-trial values

SV_VALID = {"mu": (-3.0, 3.0), "rho": (-0.99, 0.99), "sigma": (0.05, 2.0)}


@st.composite
def per_trial_cases(draw):
    """``(values, B of the call, fault or None)`` for the stochastic volatility model."""
    B = draw(st.integers(1, 4))
    names = draw(st.lists(st.sampled_from(sorted(SV_VALID)), min_size=1, max_size=3, unique=True))
    values = {n: torch.tensor([draw(st.floats(*SV_VALID[n])) for _ in range(B)], dtype=F64) for n in names}
    fault = draw(
        st.sampled_from([None, None, "name", "shape", "count", "call_count", "dtype", "nan", "domain", "list"])
    )
    n = names[0]
    if fault == "name":
        values["beta_typo"] = values.pop(n)
    elif fault == "shape":
        values[n] = values[n][:, None]
    elif fault == "count" and len(names) > 1:
        values[names[1]] = torch.cat([values[names[1]], values[names[1]][:1]])
    elif fault == "dtype":
        values[n] = values[n].float()
    elif fault == "nan":
        values[n][draw(st.integers(0, B - 1))] = draw(st.sampled_from([math.nan, math.inf]))
    elif fault == "domain" and n != "mu":
        values[n][draw(st.integers(0, B - 1))] = {"rho": draw(st.sampled_from([1.5, -1.01])), "sigma": -0.5}[n]
    elif fault == "list":
        values[n] = values[n].tolist()
    elif fault in ("count", "domain"):
        fault = None
    call_B = B + 1 if fault == "call_count" else B
    return values, call_B, fault


@given(case=per_trial_cases(), seed=st.integers(0, 2**31 - 1))
@fuzz(120)
def test_per_trial_values_run_to_finite_results_or_name_the_parameter(case, seed):
    """Per-trial values inside their declared domain give a finite filter result of the call's
    shape; a wrong name, shape, dtype, trial count, a non-finite value or one outside the model's
    declared domain (a negative sigma, |rho| > 1) is torchflow's error naming the parameter."""
    values, B, fault = case
    event(f"fault: {fault}")
    model = StochasticVolatility()
    obs = torch.linspace(-1, 1, 5, dtype=F64).reshape(1, 5, 1).expand(B, 5, 1)
    mean, cov = torch.zeros(B, 1, dtype=F64), torch.eye(1, dtype=F64).expand(B, 1, 1)
    try:
        with per_trial_values(model, values):
            res = BootstrapParticleFilter(model, n_particles=16)(obs, mean, cov, torch.Generator().manual_seed(seed))
    except TorchflowError as e:
        assert fault is not None, f"refused valid values: {e}"
        named = "beta_typo" if fault == "name" else next(iter(values))
        assert named in str(e) or fault == "count", (fault, str(e))
        assert "\n" not in str(e)
        return
    assert fault is None, f"accepted values with fault {fault}: {values}"
    assert res.estimates.shape == (B, 5, 1) and torch.isfinite(res.estimates).all()
    assert torch.isfinite(res.log_evidence).all()
    assert float(model.sigma) > 0  # the model's own values are back


def test_a_per_trial_value_outside_the_declared_domain_is_named():
    """The domain check in plain words (also the case the fuzz above draws)."""
    model = StochasticVolatility()
    with pytest.raises(TorchflowError, match=r"values\['sigma'\]: expected values in StochasticVolatility's domain"):
        with per_trial_values(model, {"sigma": torch.tensor([0.5, -0.3], dtype=F64)}):
            pass
    lg = _model()  # a model declaring names without domains takes any finite value
    with per_trial_values(lg, {"F": -torch.eye(M, dtype=F64).expand(2, M, M).clone()}):
        res = KalmanFilter(lg)(torch.zeros(2, 3, M, dtype=F64), torch.zeros(2, M, dtype=F64), torch.eye(M, dtype=F64))
    assert torch.isfinite(res.log_evidence).all()


# ----------------------------------------------------------------------------------------------
# task settings: a sweep over valid and invalid values, each job finishing or refusing in one line

SWEEPS = {
    "smooth": (
        ["task=smooth", "model=linear_gaussian", "model.d=4", "trials=2", "steps=4", "n_particles=20", "filter=[bpf]"],
        {
            "smooth.n_paths": {"5": True, "0": False, "-3": False, "2.5": False},
            "smooth.method": {"auto": True, "genealogy": True, "rts": False, "nope": False},
        },
        "smoothing.json",
    ),
    "pmmh": (
        [
            "task=pmmh",
            "model=stochastic_volatility",
            "filter=[bpf]",
            "steps=6",
            "n_particles=16",
            "+pmmh.priors={rho: {dist: Uniform, low: -1, high: 1}}",
        ],
        {
            "pmmh.chains": {"2": True, "0": False, "1.5": False},
            "pmmh.iterations": {"4": True, "3": False, "-1": False},
            "pmmh.adapt": {"0": True, "-2": False},
        },
        "pmmh.json",
    ),
}


@pytest.mark.parametrize("task", sorted(SWEEPS))
def test_task_settings_in_a_sweep_finish_or_are_refused_in_one_line(tmp_path, task):
    """Every combination of valid and invalid task settings runs as one Hydra sweep (one process):
    a job whose settings are all valid finishes (its result file holds finite numbers); every
    other job is refused in one ``error:`` line naming one of its invalid keys (its ``error.txt``),
    and the sweep goes on to the next job."""
    base, table, result = SWEEPS[task]
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    sweep = [f"{k}={','.join(v)}" for k, v in table.items()]
    args = [*base, "progress=false", "plots=false", "checkpoint_dir=null", f"hydra.sweep.dir={tmp_path / 'sw'}"]
    out = subprocess.run(
        [sys.executable, "-m", "torchflow", "-m", *args, *sweep],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=env,
        timeout=600,
    )
    assert "Traceback" not in out.stderr, out.stderr[-3000:]
    jobs = sorted((tmp_path / "sw").glob("[0-9]*"), key=lambda p: int(p.name))
    assert len(jobs) == math.prod(len(v) for v in table.values()), out.stderr[-2000:]
    for job in jobs:
        overrides = dict(
            o.split("=", 1) for o in (job / ".hydra" / "overrides.yaml").read_text().split("- ")[1:] if "=" in o
        )
        chosen = {k: overrides[k].strip() for k in table}
        bad = [k for k, v in chosen.items() if not table[k][v]]
        if not bad:
            assert (job / result).exists(), (chosen, out.stderr[-2000:])
            assert "NaN" not in (job / result).read_text() and "Infinity" not in (job / result).read_text()
        else:
            error = (job / "error.txt").read_text().strip()
            assert error.startswith("error: ") and "\n" not in error, (chosen, error)
            assert any(k in error for k in bad), (chosen, error)
            assert not (job / result).exists()
