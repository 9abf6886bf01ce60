"""Property-based fuzz of input validation: every call either returns finite results of the inputs'
shapes or raises torchflow's own error naming what was wrong (:mod:`torchflow.core.errors`), never a raw
torch error and never a silent broadcast.

* every filter's ``forward`` on a small linear-Gaussian model, with bad observations, priors,
  generators and particle counts planted one or two at a time;
* the models' constructors with bad matrices and keyword values;
* user models whose methods return outputs of the wrong shape (compared with the same model
  without the mistake: a result that differs is a silent broadcast);
* the runner's settings (``run_experiment``).

Examples are drawn by ``hypothesis`` with ``derandomize=True`` and no example database, so every run
(and CI) draws the same examples. ``TORCHFLOW_FUZZ_EXAMPLES=3000`` fuzzes deeper with fresh examples.
"""

from __future__ import annotations

import functools
import math
import os
import re
import warnings

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

import torchflow.filters as F
from torchflow.app.runner import run_experiment
from torchflow.core.errors import NonFiniteError, TorchflowError
from torchflow.core.random import TrialStreams
from torchflow.flows.schedules import ExponentialSchedule
from torchflow.models import (
    TDOA3D,
    AcousticTracking,
    GaussianStateSpaceModel,
    LinearGaussian,
    SensorNetwork,
    SkewedTPoisson,
    StochasticVolatility,
)

#: fresh random examples, this many per test (0: the fixed examples CI runs)
DEEP = int(os.environ.get("TORCHFLOW_FUZZ_EXAMPLES", "0"))
FUZZ = settings(
    deadline=None,
    derandomize=not DEEP,
    database=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
)


def fuzz(examples: int):
    """The settings of one fuzz test: ``examples`` fixed examples (``DEEP`` random ones if set)."""
    return settings(FUZZ, max_examples=DEEP or examples)


DEAD_STEP = "no particle's weight carried the measurement"
NONFINITE = [math.nan, math.inf, -math.inf]


@functools.lru_cache(maxsize=None)
def lg(d: int, m: int, dtype: torch.dtype = torch.float64) -> LinearGaussian:
    """A small linear-Gaussian model (shared between examples: never modified)."""
    return new_lg(d, m, dtype)


def new_lg(d: int, m: int, dtype: torch.dtype = torch.float64) -> LinearGaussian:
    eye = torch.eye(d, dtype=torch.float64)
    model = LinearGaussian(
        0.9 * eye,
        0.2 * eye,
        torch.eye(m, d, dtype=torch.float64) + 0.1,
        0.1 * torch.eye(m, dtype=torch.float64),
        torch.zeros(d, dtype=torch.float64),
        eye,
    )
    return model.to(dtype)


def short():
    return ExponentialSchedule(n_steps=3)


#: every filter family on a small model: few particles, short flows
FILTERS = {
    "kf": lambda m: F.KalmanFilter(m),
    "ekf": lambda m: F.ExtendedKalmanFilter(m),
    "ukf": lambda m: F.UnscentedKalmanFilter(m),
    "bpf": lambda m: F.BootstrapParticleFilter(m, n_particles=8),
    "pfpf_edh": lambda m: F.ParticleFlowParticleFilter(m, flow="edh", n_particles=8, schedule=short()),
    "pfpf_ledh": lambda m: F.ParticleFlowParticleFilter(m, flow="ledh", n_particles=8, schedule=short()),
    "flow_filter": lambda m: F.ParticleFlowFilter(m, flow="edh", n_particles=8, schedule=short()),
    "gpfis": lambda m: F.GPFIS(m, n_particles=8, schedule=short()),
    "gpf": lambda m: F.GaussianParticleFilter(m, n_particles=8),
    "gspf": lambda m: F.GaussianSumParticleFilter(m, n_components=2, particles_per_component=6),
}
DTYPES = [torch.float64, torch.float32, torch.int64, torch.float16, torch.bool, torch.complex128, torch.bfloat16]


# ---- the property ---------------------------------------------------------------------------------


def check_outcome(call, blame, shape, *, extreme=False, particles=False, memory=False, name=None):
    """``call()`` returns finite results of ``shape = (B, T, d)`` or raises a :class:`TorchflowError`
    naming one of ``blame`` (the planted faults; none: the call must run). With ``extreme`` (finite
    inputs far in the tails) a :class:`NonFiniteError` naming the filter will do; with ``memory`` (a
    request no machine holds) a ``MemoryError`` saying what was asked. A particle filter may warn that
    a step carried no measurement: that trial's increment is then ``-inf`` (``guards.py``,
    nonfinite='recover') and nothing else is non-finite."""
    B, T, d = shape
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            out = call()
        except MemoryError as err:
            assert memory and "out of memory running" in str(err), repr(err)
            return err
        except NonFiniteError as err:
            assert extreme or any(b in str(err) for b in blame), f"{err!r} (planted: {sorted(blame)})"
            assert name is None or err.filter_name == name, f"{err!r} does not name the filter {name!r}"
            return err
        except TorchflowError as err:
            assert blame, f"valid inputs refused: {err!r}"
            assert any(b in str(err) for b in blame), f"{err!r} names none of {sorted(blame)}"
            return err
    assert not blame, f"accepted {sorted(blame)}"
    assert tuple(out.estimates.shape) == (B, T, d)
    assert tuple(out.log_evidence.shape) == (B,)
    assert tuple(out.log_evidence_increments.shape) == (B, T)
    assert torch.isfinite(out.estimates).all()
    dead = [w for w in caught if issubclass(w.category, RuntimeWarning) and DEAD_STEP in str(w.message)]
    inc = out.log_evidence_increments
    if dead:
        assert particles, "only particle filters have steps that carry no measurement"
        assert (inc[~torch.isfinite(inc)] == -math.inf).all()
    else:
        assert torch.isfinite(inc).all()
    if out.ess is not None:
        assert tuple(out.ess.shape) == (B, T) and torch.isfinite(out.ess).all()
    if out.covariances is not None:
        assert tuple(out.covariances.shape) == (B, T, d, d) and torch.isfinite(out.covariances).all()
    if out.particles is not None:
        assert out.particles.shape[:2] == (B, T) and out.particles.shape[-1] == d
        assert tuple(out.log_weights.shape) == tuple(out.particles.shape[:-1])
    return out


# ---- strategies: (value, tag) with tag None (valid), "extreme" (valid, far in the tails) or the
# ---- argument's name (a planted fault) ----------------------------------------------------------------


def nonfinite_at(draw, x, values=NONFINITE):
    """A copy of ``x`` with NaN or +-inf (one of ``values``) at a drawn position."""
    x = x.clone()
    x.view(-1)[draw(st.integers(0, x.numel() - 1))] = draw(st.sampled_from(values))
    return x


def far(dtype):
    """Finite values far in the tails of ``dtype`` (and one far below 1)."""
    big = torch.finfo(dtype).max
    return st.sampled_from([big / 10, -(big**0.5), big**0.8, torch.finfo(dtype).tiny * 10])


def other_dtype(draw, dtype):
    return draw(st.sampled_from([t for t in DTYPES if t != dtype]))


#: the faults planted in a forward call: argument -> kinds of bad value (some depend on B, d: see below)
BAD = {
    "observations": ["ndim2", "ndim4", "m", "B0", "T0", "dtype", "nonfinite", "meta", "list", "none", "numpy"],
    "mean": ["one", "d", "wrongB", "wrongd", "col", "dtype", "nonfinite", "meta", "scalar", "list"],
    "cov": ["one", "variances", "wrongB", "wrongd", "dtype", "nonfinite", "nonpsd", "asym", "meta", "list", "vector"],
    "generator": ["none", "int", "str", "streams", "numpy", "state"],
    "n_particles": [0, -1, 1.5, True, "8", 2**62, math.nan, [4]],
}
PLANTS = [(arg, kind) for arg, kinds in BAD.items() for kind in kinds]
HUGE = 2**62


@st.composite
def observations(draw, B, T, m, dtype, kind, extreme_ok):
    z = torch.randn(B, T, m, generator=torch.Generator().manual_seed(draw(st.integers(0, 9)))).to(dtype)
    if kind is None:
        kind = draw(st.sampled_from(["ok"] * 6 + ["noncontiguous"] + ["extreme"] * extreme_ok))
        if kind == "noncontiguous":
            return z.transpose(0, 1).contiguous().transpose(0, 1), None
        if kind == "extreme":
            z.view(-1)[draw(st.integers(0, z.numel() - 1))] = draw(far(dtype))
            return z, "extreme"
        return z, None
    z = {
        "ndim2": lambda: z[:, 0],
        "ndim4": lambda: z.unsqueeze(draw(st.integers(0, 3))),
        "m": lambda: torch.randn(B, T, m + draw(st.sampled_from([-m, 1, 2]))).to(dtype),
        "B0": lambda: z[:0],
        "T0": lambda: z[:, :0],
        "dtype": lambda: z.to(other_dtype(draw, dtype)),
        # NaN in the observations means "not observed": only an infinity is a fault there
        "nonfinite": lambda: nonfinite_at(draw, z, [v for v in NONFINITE if v == v]),
        "meta": lambda: z.to("meta"),
        "list": z.tolist,
        "none": lambda: None,
        "numpy": lambda: z.numpy(),
    }[kind]()
    return z, "observations"


@st.composite
def means(draw, B, d, dtype, kind, extreme_ok):
    base = torch.zeros(B, d, dtype=dtype)
    if kind is None:
        kind = draw(
            st.sampled_from(["B"] * 4 + ["shared", "shared"] + ["extreme"] * extreme_ok + (["one"] if B == 1 else []))
        )
        if kind == "extreme":
            return torch.full((B, d), draw(far(dtype)), dtype=dtype), "extreme"
        return (base[0] if kind == "shared" else base), None
    if kind == "one" and B == 1:  # (1, d) is valid then
        kind = "wrongB"
    mean = {
        "one": lambda: base[:1],  # (1, d) is not broadcast over B trials
        "d": lambda: torch.zeros(d + 1, dtype=dtype),
        "wrongB": lambda: torch.zeros(B + draw(st.sampled_from([1, 2])), d, dtype=dtype),
        "wrongd": lambda: torch.zeros(B, d + 1, dtype=dtype),
        "col": lambda: base.unsqueeze(-1),
        "dtype": lambda: base.to(other_dtype(draw, dtype)),
        "nonfinite": lambda: nonfinite_at(draw, base),
        "meta": lambda: base.to("meta"),
        "scalar": lambda: torch.tensor(0.0, dtype=dtype),
        "list": base.tolist,
    }[kind]()
    return mean, "mean"


@st.composite
def covs(draw, B, d, dtype, kind, extreme_ok):
    eye = torch.eye(d, dtype=dtype)
    base = eye.repeat(B, 1, 1)
    if kind is None:
        kind = draw(
            st.sampled_from(
                ["B"] * 4
                + ["shared", "expanded", "singular", "near_psd"]
                + ["extreme"] * extreme_ok
                + (["one"] if B == 1 else [])
                + (["variances"] if B == d else [])
            )
        )
        if kind == "near_psd":  # singular, with a round-off negative eigenvalue: within check_psd's tolerance
            return torch.ones(B, d, d, dtype=dtype) - (1e-13 if dtype == torch.float64 else 1e-8) * eye, None
        if kind == "extreme":
            return base * abs(draw(far(dtype))), "extreme"
        cov = {
            "B": base,
            "shared": eye,
            "expanded": eye.expand(B, d, d),
            "singular": torch.zeros_like(base),
            "one": base,
            "variances": torch.ones(B, d, dtype=dtype),
        }[kind]
        return cov, None
    # valid where B = 1 ("one"), B = d ("variances": a (d, d) matrix then), d = 1 ("asym")
    kind = {
        "one": "wrongB" if B == 1 else "one",
        "variances": "wrongd" if B == d else "variances",
        "asym": "nonpsd" if d == 1 else "asym",
    }.get(kind, kind)
    if kind == "nonpsd":  # a negative variance; -1e-13 is not round-off in a matrix of zeros
        zeros = draw(st.booleans())
        cov = torch.zeros_like(base) if zeros else base.clone()
        cov[draw(st.integers(0, B - 1)), 0, 0] = -draw(st.sampled_from([1e-13] * zeros + [1e-3, 1.0, 1e6]))
    elif kind == "asym":
        cov = base.clone()
        cov[draw(st.integers(0, B - 1)), 0, 1] = 0.5
    else:
        cov = {
            "one": lambda: base[:1],
            "variances": lambda: torch.ones(B, d, dtype=dtype),
            "wrongB": lambda: eye.repeat(B + 1, 1, 1),
            "wrongd": lambda: torch.eye(d + 1, dtype=dtype).repeat(B, 1, 1),
            "dtype": lambda: base.to(other_dtype(draw, dtype)),
            "nonfinite": lambda: nonfinite_at(draw, base),
            "meta": lambda: base.to("meta"),
            "list": base.tolist,
            "vector": lambda: eye[0],
        }[kind]()
    return cov, "cov"


@st.composite
def generators(draw, B, kind):
    if kind is None:
        if draw(st.booleans()):
            return torch.Generator().manual_seed(draw(st.integers(0, 3))), None
        return TrialStreams(draw(st.integers(0, 3)), B, backend=draw(st.sampled_from(["numpy", "philox"]))), None
    gen = {
        "none": lambda: None,
        "int": lambda: 3,
        "str": lambda: "seed",
        "numpy": lambda: np.random.default_rng(0),
        "streams": lambda: TrialStreams(0, B + draw(st.sampled_from([1, 3]))),  # made for other trials
        "state": lambda: torch.Generator().get_state(),
    }[kind]()
    return gen, "generator"


GOOD_N = st.sampled_from([None, None, 1, 2, 3.0, np.int64(4)])


def forward_case(data, name, d, m, B, T, dtype, plants, returns):
    """One forward call with ``plants`` (``(argument, kind)`` faults), the other arguments valid (far
    in the tails only when nothing is planted: a NonFiniteError must not excuse a missed refusal)."""
    f = FILTERS[name](lg(d, m, dtype))
    kinds, extreme_ok = dict(plants), not plants
    drawn = {
        "observations": data.draw(observations(B, T, m, dtype, kinds.get("observations"), extreme_ok), "z"),
        "mean": data.draw(means(B, d, dtype, kinds.get("mean"), extreme_ok), "mean"),
        "cov": data.draw(covs(B, d, dtype, kinds.get("cov"), extreme_ok), "cov"),
        "generator": data.draw(generators(B, kinds.get("generator")), "generator"),
    }
    n = kinds["n_particles"] if "n_particles" in kinds else data.draw(GOOD_N, "n_particles")
    tags = {k: tag for k, (_, tag) in drawn.items() if f.uses_randomness or k != "generator"}
    if "n_particles" in kinds and (f.n_particles is not None or not (isinstance(n, int) and n == HUGE)):
        tags["n_particles"] = "n_particles"  # checked as a count by every filter (one without particles ignores it)
    if name in ("gpf", "gspf") and n is not None and n != f.n_particles:
        tags["n_particles"] = "n_particles"  # a Gaussian-sum filter's total comes from its components
    blame = {t for t in tags.values() if t not in (None, "extreme")}
    z, mean, cov, gen = (drawn[k][0] for k in ("observations", "mean", "cov", "generator"))
    out = check_outcome(
        lambda: f(z, mean, cov, gen, n_particles=n, return_covariances=returns[0], return_particles=returns[1]),
        blame,
        (B, T, d),
        extreme="extreme" in tags.values(),
        particles=f.uses_particles,
        memory=isinstance(n, int) and n == HUGE and "n_particles" in blame,
        name=f.name,
    )
    event(type(out).__name__)


CASE = dict(
    data=st.data(),
    name=st.sampled_from(sorted(FILTERS)),
    d=st.integers(1, 3),
    m=st.integers(1, 3),
    B=st.integers(1, 3),
    T=st.integers(1, 3),
    dtype=st.sampled_from([torch.float64, torch.float32]),
    returns=st.sampled_from([(False, False), (True, False), (False, True)]),
)


@given(**CASE)
@fuzz(300)
def test_every_filter_runs_valid_inputs_to_finite_results(data, name, d, m, B, T, dtype, returns):
    forward_case(data, name, d, m, B, T, dtype, [], returns)


@pytest.mark.parametrize("plant", PLANTS, ids=[f"{a}={k!r}" for a, k in PLANTS])
@given(second=st.one_of(st.none(), st.sampled_from(PLANTS)), **CASE)
@fuzz(20)
def test_every_filter_names_each_bad_argument(plant, second, data, name, d, m, B, T, dtype, returns):
    """Every kind of bad value, on several filters and shapes, alone or with a second fault."""
    plants = [plant] + ([second] if second is not None and second[0] != plant[0] else [])
    forward_case(data, name, d, m, B, T, dtype, plants, returns)


# ---- the models' constructors -----------------------------------------------------------------------


def check_construction(make, blame):
    """``make()`` raises a :class:`TorchflowError` naming one of ``blame``, or (nothing planted)
    builds a model whose buffers are finite and whose simulation is finite or a NonFiniteError
    naming the model (a valid but extreme parameter)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a cast that drops something (complex -> real) warns: it must refuse
        try:
            model = make()
        except TorchflowError as err:
            assert blame, f"valid arguments refused: {err!r}"
            assert any(b in str(err) for b in blame), f"{err!r} names none of {sorted(blame)}"
            return err
    assert not blame, f"accepted {sorted(blame)}"
    for name, buf in model.named_buffers():
        assert buf is None or not buf.is_floating_point() or torch.isfinite(buf).all(), name
    if not isinstance(model, TDOA3D):  # a localisation model: its data are measurement sets
        try:
            traj = model.simulate(1, 2, torch.Generator().manual_seed(0))
        except NonFiniteError as err:
            assert type(model).__name__ in str(err)
            return err
        assert torch.isfinite(traj.states).all() and torch.isfinite(traj.observations).all()
    return model


def psd(d, seed, rank=None):
    A = torch.randn(d, rank or d, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    return A @ A.T + (0.0 if rank else 0.1) * torch.eye(d, dtype=torch.float64)


#: kinds of bad matrix (a covariance also non-PSD or asymmetric; m0 and P0 may be None: zeros)
MATRIX_BAD = [
    "transposed_or_bigger",
    "vector",
    "scalar",
    "extra_dim",
    "nonfinite",
    "str",
    "complex",
    "meta",
    "empty",
    "none",
    "nonpsd",
    "asym",
]
LG_SHAPES = {"F": "matrix", "Q": "cov", "H": "matrix", "R": "cov", "m0": "vector", "P0": "cov"}
LG_PLANTS = (
    [
        (arg, kind)
        for arg, of in LG_SHAPES.items()
        for kind in MATRIX_BAD
        if not (kind == "none" and arg in ("m0", "P0")) and (of == "cov" or kind not in ("nonpsd", "asym"))
    ]
    + [("learnable", v) for v in (5, None, ["X"], "FX", 1.5)]
    + [("measurement_noise", v) for v in ("full", 3, "scalar")]
)


@st.composite
def matrix_arg(draw, name, shape, kind_of_matrix, kind):
    """A valid matrix (a tensor, array or nested list, in any real dtype) or the bad ``kind``."""
    seed = draw(st.integers(0, 5))
    rank = draw(st.sampled_from([None, None, 1])) if name == "P0" else None  # P0 may be singular
    if kind_of_matrix == "cov":
        good = psd(shape[0], seed, rank=rank)
    else:
        good = torch.randn(*shape, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    if kind is None:  # float32 rounding leaves a singular matrix a little indefinite in float64: not for those
        form = draw(st.sampled_from(["tensor", "numpy", "list"] + ([] if rank else ["float32"])))
        return {"tensor": good, "float32": good.float(), "numpy": good.numpy(), "list": good.tolist()}[form]
    if kind == "transposed_or_bigger":
        return good.T if len(shape) == 2 and shape[0] != shape[1] else torch.zeros(*[s + 1 for s in shape])
    if kind in ("nonpsd", "asym"):
        bad_cov = good.clone()
        if kind == "asym" and shape[0] > 1:
            bad_cov[0, -1] += 1.0
        else:
            bad_cov[0, 0] = -1.0
        return bad_cov
    return {
        "vector": lambda: good.reshape(-1) if len(shape) == 2 else good[:1].reshape(1, 1),
        "scalar": lambda: torch.tensor(1.0),
        "extra_dim": lambda: good.unsqueeze(0),
        "nonfinite": lambda: nonfinite_at(draw, good),
        "str": lambda: "abc",
        "none": lambda: None,
        "complex": lambda: good.to(torch.complex128) * (1 + 1j),
        "meta": lambda: good.to("meta"),
        "empty": lambda: torch.zeros(*[0 for _ in shape]),
    }[kind]()


def linear_gaussian_case(data, d, m, plants):
    kinds = dict(plants)
    shapes = {"F": (d, d), "Q": (d, d), "H": (m, d), "R": (m, m), "m0": (d,), "P0": (d, d)}
    args = {k: data.draw(matrix_arg(k, shapes[k], LG_SHAPES[k], kinds.get(k)), k) for k in shapes}
    learnable = kinds.get("learnable", data.draw(st.sampled_from([False, True, ["F"], "H", ("Q", "R")]), "learnable"))
    noise = kinds.get("measurement_noise", data.draw(st.sampled_from([None, "dense"]), "measurement_noise"))
    r_learnt = learnable is True or isinstance(learnable, (list, tuple)) and "R" in learnable
    scalar_ok = m == 1 and noise == "scalar" and not r_learnt  # a fixed 1 x 1 R is a scalar R
    blame = set(kinds) - ({"measurement_noise"} if scalar_ok else set())
    check_construction(
        lambda: LinearGaussian(
            args["F"],
            args["Q"],
            args["H"],
            args["R"],
            args["m0"],
            args["P0"],
            learnable=learnable,
            measurement_noise=noise,
        ),
        blame,
    )


DIMS = dict(data=st.data(), d=st.integers(1, 3), m=st.integers(1, 3))


@given(**DIMS)
@fuzz(100)
def test_linear_gaussian_builds_a_finite_model_from_valid_matrices(data, d, m):
    linear_gaussian_case(data, d, m, [])


@pytest.mark.parametrize("plant", LG_PLANTS, ids=[f"{a}={k!r}" for a, k in LG_PLANTS])
@given(second=st.one_of(st.none(), st.sampled_from(LG_PLANTS)), **DIMS)
@fuzz(8)
def test_linear_gaussian_names_each_bad_matrix(plant, second, data, d, m):
    linear_gaussian_case(data, d, m, [plant] + ([second] if second is not None and second[0] != plant[0] else []))


#: keyword -> (valid values, bad values) of each model's constructor
MODEL_KWARGS = {
    AcousticTracking: {
        "sigma_w": ([0.1, 1.0, 1e-3], [0, -1, math.nan, math.inf, "0.1", True, None, 1e-300, 1e200]),
        "psi": ([10.0, 1, 1e3], [0, -5, math.nan, math.inf, "x", True]),
        "d0": ([0.1, 1.0], [0, -1, math.nan, math.inf, "x", False]),
        "true_noise_scale": ([0.05, 1.0], [0, -1, math.nan, math.inf, "x"]),
        "filter_noise": (["inflated", "truth", True], ["none", 3, None, False]),
        "area": ([40.0, 50], [0, -1, math.nan, math.inf, "40", 10]),  # 10: the targets start outside
        "sensor_grid": ([1, 2, 3.0], [0, -1, 2.5, "5", True, math.nan]),
        "prior_std": (
            [(10, 10, 1, 1), [1.0, 1, 1, 1], np.ones(4)],
            [(1, 1, -1, 1), (1, 1, 1), 5.0, "abcd", (math.nan, 1, 1, 1), None, (1j, 1, 1, 1)],
        ),
        "initial_state": (
            [None, [12.0, 6, 0.001, 0.001, 32, 32, -0.001, -0.005, 20, 13, -0.1, 0.01, 15, 35, 0.002, 0.002]],
            [[1.0] * 15, [math.nan] * 16, "abc", 5.0],
        ),
        "margin": ([0.05, 0, 0.1], [0.5, -0.1, math.nan, "x", 0.49]),
        "max_redraws": ([10000, 1], [0, 1.5, -1, "x"]),
        "learnable": ([False, True, ["psi"], "sigma_w"], [["d0"], 5, None, "x"]),
    },
    SensorNetwork: {
        "d": ([1, 4, 9, 4.0], [0, -4, 5, 2.5, "4", True, math.nan]),
        "alpha": ([0.9, 0, -0.5, 1.5], [math.nan, math.inf, "x", True, None]),
        "alpha0": ([3, 0, 1e300], [-1, math.nan, math.inf, "x"]),
        "alpha1": (
            [0.01, 1, 0],
            [-1, math.nan, math.inf],
        ),  # alpha0 = alpha1 = 0 is Q = 0 (filters that need Q > 0 refuse it)
        "beta": ([20, 0.5, 1e-300], [0, -1, math.nan, math.inf, "x"]),
        "sigma_z": ([0.5, 1e-3], [0, -1, math.nan, math.inf, 1e200]),
        "prior_var": ([0, 1], [-1, math.nan, math.inf, "x"]),
        "learnable": ([False, True], ["yes", 5, None]),
    },
    SkewedTPoisson: {
        "d": ([1, 4], [0, 5, 4.0, "4", True, -4]),
        "alpha": ([0.9, 0], [math.nan, math.inf, "x", True]),
        "gamma": ([0.3, 0, -1], [math.nan, math.inf, "x", 1e200]),
        "nu": ([7, 5, 100], [4, 3, 7.0, "7", True, math.nan]),
        "alpha0": ([3.0, 0], [-1, math.nan, math.inf]),
        "alpha1": ([0.01, 1], [0, -1, math.nan]),
        "beta": ([20.0, 1], [0, -1, math.inf]),
        "m1": ([1.0, 2], [0, -1, math.nan]),
        "m2": ([1 / 3, 0, -1], [math.nan, math.inf, "x"]),
    },
    StochasticVolatility: {
        "mu": ([-1.02, 0, 3.5], [math.nan, math.inf, "x", True, None]),
        "rho": ([0.9702, 0, -0.5, 0.999], [1, -1, 1.5, math.nan, "0.9", True]),
        "sigma": ([0.178, 1, 1e-3], [0, -0.1, math.nan, math.inf, "x"]),
        "gaussian_form": (["returns", "log_squared"], ["log", 3, None, True]),
        "offset": ([0.0, 1e-4, 1], [-1, math.nan, math.inf, "x"]),
        "learnable": ([False, True, ["rho"], "sigma"], [["phi"], 5, None, "x"]),
    },
    TDOA3D: {
        "speed": ([1500.0, 1], [0, -1, math.nan, math.inf, "x", True]),
        "sigma_v": ([5e-4, 1], [0, -1, math.nan, math.inf]),
        "p_d": ([0.95, 1, 0.01], [0, 1.5, -0.1, math.nan]),
        "clutter_rate": ([1.0, 0, 10], [-1, math.nan, math.inf, "x"]),
        "n_sources": ([3, 0, 1], [-1, 1.5, "3", True, 3.0]),
        "region": ([1000.0, 1, 1e300], [0, -1, math.nan, math.inf, "x"]),
        "receivers": (
            [None],
            [
                torch.zeros(3, 2),
                torch.zeros(1, 3),
                torch.zeros(2, 3),
                "abc",
                torch.tensor([[0.0, 0, 0], [math.nan, 1, 1]]),
                torch.ones(2, 3, dtype=torch.complex64),
            ],
        ),
        "pairs": ([None], [[], [(0, 0)], [(0, 99)], [(0,)], [(0.5, 1)], [("a", 1)], 5]),
    },
}


def keyword_case(data, table, plants):
    """Keyword arguments: some keywords of ``table`` at drawn valid values, ``plants`` (``(keyword,
    bad value)``) at theirs; and the keywords to blame."""
    chosen = data.draw(st.sets(st.sampled_from(sorted(table)), max_size=4), "keywords")
    kwargs = {k: data.draw(st.sampled_from(table[k][0]), k) for k in chosen}
    kwargs.update(plants)
    return kwargs, {k for k, _ in plants}


def plants_of(table):
    return [(k, v) for k, (_, bad) in table.items() for v in bad]


SMALL = {SkewedTPoisson: {"d": 4}, SensorNetwork: {"d": 4}}  # the default sizes cost time, not coverage
MODEL_PLANTS = [(model, plant) for model, table in MODEL_KWARGS.items() for plant in plants_of(table)]


def model_case(data, model, plants):
    kwargs, blame = keyword_case(data, MODEL_KWARGS[model], plants)
    check_construction(lambda: model(**{**SMALL.get(model, {}), **kwargs}), blame)


@given(data=st.data(), model=st.sampled_from(list(MODEL_KWARGS)))
@fuzz(80)
def test_every_model_builds_from_valid_keywords(data, model):
    model_case(data, model, [])


@pytest.mark.parametrize("model, plant", MODEL_PLANTS, ids=[f"{m.__name__}-{k}={v!r}" for m, (k, v) in MODEL_PLANTS])
@given(data=st.data())
@fuzz(4)
def test_every_model_names_each_bad_keyword(model, plant, data):
    second = data.draw(st.one_of(st.none(), st.sampled_from(plants_of(MODEL_KWARGS[model]))), "second")
    model_case(data, model, [plant] + ([second] if second is not None and second[0] != plant[0] else []))


# ---- user models whose methods return the wrong shape ------------------------------------------------


def wrong_shape(out, how):
    """``out`` reshaped the way a user's method might get it wrong (several still broadcast)."""
    if how == "drop":  # (..., 1): broadcasts
        return out[..., :1]
    if how == "extra":
        return out.unsqueeze(-1)
    if how == "sum":
        return out.sum(-1)
    if how == "lead":  # (1, ...): broadcasts
        return out.unsqueeze(0)
    if how == "pad":
        return torch.cat([out, out[..., :1]], -1)
    if how == "flatten":  # (B N, k) from (B, N, k): right on (B, d) inputs only
        return out.reshape(-1, out.shape[-1]) if out.dim() else out
    if how == "first":  # the first trial's output for all: broadcasts
        return out[:1] if out.dim() else out
    if how == "scalar":
        return out.sum()
    return out.transpose(-1, -2) if out.dim() >= 2 else out  # "transpose"


METHODS = (
    "transition_mean",
    "measure",
    "transition_cov",
    "measurement_cov",
    "sample_transition",
    "sample_measurement",
    "transition_log_prob",
    "measurement_log_prob",
    "initial_state",
)
WRONG = ("drop", "extra", "sum", "lead", "pad", "flatten", "first", "scalar", "transpose")


class UserModel(GaussianStateSpaceModel):
    """A linear-Gaussian model written by hand, as a user would; ``bug = (method, how)`` gets one
    method's output shape wrong."""

    def __init__(self, d, m, bug=None):
        super().__init__()
        self.state_dim, self.obs_dim, self.bug = d, m, bug
        self.register_buffer("A", 0.9 * torch.eye(d, dtype=torch.float64))
        self.register_buffer("H", torch.eye(m, d, dtype=torch.float64) + 0.1)
        self.register_buffer("Q", 0.2 * torch.eye(d, dtype=torch.float64))
        self.register_buffer("R", 0.1 * torch.eye(m, dtype=torch.float64))

    def _out(self, method, out):
        return wrong_shape(out, self.bug[1]) if self.bug is not None and self.bug[0] == method else out

    def transition_mean(self, x):
        return self._out("transition_mean", x @ self.A.T)

    def transition_cov(self, x=None):
        return self._out("transition_cov", self.Q)

    def measure(self, x):
        return self._out("measure", x @ self.H.T)

    def measurement_cov(self, x=None):
        return self._out("measurement_cov", self.R)

    def sample_transition(self, x, generator=None):
        return self._out("sample_transition", super().sample_transition(x, generator))

    def sample_measurement(self, x, generator=None):
        return self._out("sample_measurement", super().sample_measurement(x, generator))

    def transition_log_prob(self, x_next, x):
        return self._out("transition_log_prob", super().transition_log_prob(x_next, x))

    def measurement_log_prob(self, z, x):
        return self._out("measurement_log_prob", super().measurement_log_prob(z, x))

    def initial_state(self, batch_size, generator=None):
        return self._out("initial_state", torch.zeros(batch_size, self.state_dim, dtype=torch.float64))


def same_or_named(run, clean, method):
    """``run()`` (the model with the mistake) raises a :class:`TorchflowError` naming ``method``, or
    returns what ``clean()`` (the same model without it) returns: a different result is a silent
    broadcast."""
    expected = clean()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a broadcast that kills every weight warns; the comparison judges it
        try:
            got = run()
        except TorchflowError as err:
            assert re.search(rf"\b{method}\b", str(err)), f"{err!r} does not name {method}"
            return err
    for key in ("estimates", "log_evidence_increments", "states", "observations"):
        a, b = getattr(got, key, None), getattr(expected, key, None)
        if b is not None:
            assert a.shape == b.shape and torch.allclose(a, b, rtol=1e-9, atol=1e-12), (
                f"a silent broadcast: {key} differs from the model's without the mistake"
            )
    return got


USER_FILTERS = [k for k in FILTERS if k not in ("kf", "gspf")]  # the Kalman filter needs a declared linear model


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("how", WRONG)
@given(
    d=st.integers(1, 3),
    m=st.integers(1, 3),
    B=st.integers(1, 3),
    T=st.integers(1, 2),
    target=st.sampled_from(USER_FILTERS + ["simulate"]),
)
@fuzz(6)
def test_a_user_method_of_the_wrong_shape_is_named_never_broadcast(method, how, d, m, B, T, target):
    z = torch.randn(B, T, m, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    mean, cov = torch.zeros(B, d, dtype=torch.float64), torch.eye(d, dtype=torch.float64)

    def call(bug):
        model = UserModel(d, m, bug)
        if target == "simulate":
            return model.simulate(B, T, torch.Generator().manual_seed(1))
        f = FILTERS[target](model)
        return f(z, mean, cov, torch.Generator().manual_seed(1))

    same_or_named(lambda: call((method, how)), lambda: call(None), method)


def test_a_user_method_right_on_the_batch_but_wrong_on_particles_is_named():
    """``measure`` that flattens its leading dims is right on ``(B, d)`` and wrong on the particles
    ``(B, N, d)``, where it raised a raw broadcasting error (or broadcast silently)."""
    z = torch.randn(3, 2, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    f = F.BootstrapParticleFilter(UserModel(2, 2, ("measure", "flatten")), n_particles=8)
    with pytest.raises(
        TorchflowError,
        match=r"UserModel\.measure returned shape \(8, 2\) on the particles' layout; "
        r"expected \(B, N, m\) = \(2, 4, 2\)",
    ):
        f(z, torch.zeros(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64), torch.Generator().manual_seed(1))


def test_a_user_method_that_transposes_is_named_where_the_batch_hides_it():
    """With B = m a transposed ``measure`` has the right shape on ``(B, d)``; the unscented filter's
    sigma points broadcast it silently into other numbers."""
    z = torch.randn(2, 2, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    f = F.UnscentedKalmanFilter(UserModel(1, 2, ("measure", "transpose")))
    with pytest.raises(TorchflowError, match=r"UserModel\.measure returned shape \(2, 2, 3\) on the particles' layout"):
        f(z, torch.zeros(1, dtype=torch.float64), torch.eye(1, dtype=torch.float64))


def test_a_constant_covariance_of_the_wrong_shape_is_named_by_its_method():
    z = torch.randn(1, 2, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    f = F.ExtendedKalmanFilter(UserModel(2, 1, ("transition_cov", "drop")))
    with pytest.raises(TorchflowError, match=r"UserModel\.transition_cov returned shape \(2, 1\); expected \(d, d\)"):
        f(z, torch.zeros(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64))


def test_gpfis_runs_on_a_hand_written_model_with_the_default_hessian():
    """The default ``measurement_hessian`` (jvp over the vmapped Jacobian) crashed the process with a
    segmentation fault on torch 2.13 (a negative ``out_dims``); it runs, and is exact on a quadratic h."""
    z = torch.randn(2, 2, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    out = F.GPFIS(UserModel(2, 2), n_particles=8, schedule=short())(
        z, torch.zeros(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64), torch.Generator().manual_seed(1)
    )
    assert torch.isfinite(out.estimates).all()

    class Quadratic(UserModel):
        def measure(self, x):  # h_a = x^T A_a x
            return torch.einsum("...i,aij,...j->...a", x, self.A.expand(2, 2, 2), x)

    model = Quadratic(2, 2)
    x = torch.randn(3, 4, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    A = model.A.expand(2, 2, 2)
    assert torch.allclose(model.measurement_hessian(x), (A + A.transpose(-1, -2)).expand(3, 4, 2, 2, 2))


# ---- the runner's settings ------------------------------------------------------------------------

#: setting -> (valid values, bad values); sizes stay tiny (a huge valid size would be run)
RUN_SETTINGS = {
    "trials": ([1, 2, 3, 2.0], [0, -1, 1.5, "abc", True, math.nan]),  # None: the default (10, or the data's)
    "steps": ([1, 2], [0, -2, 2.5, "3"]),
    "seed": ([0, 7, 2**63 - 1], [-1, 2**63, 1.5, "0", None]),
    "inits_per_track": ([1, 2, 5], [0, -1, 1.5, "2"]),
    "chunk_size": ([None, 1, 2, 100], [0, -3, 2.5, "1", True]),
    "memory_budget_gb": ([4.0, 1e-6, 1e6], [0, -1, math.nan, math.inf, "4", True]),
    "device": (
        ["cpu", torch.device("cpu")],
        ["tpu", "meta", "cuda:x", 3, None] + ([] if torch.cuda.is_available() else ["cuda"]),
    ),
    "dtype": (["float64", "float32", "double", torch.float64, torch.float32], ["float16", "int64", None, 5]),
    "rng_backend": (["auto", "numpy", "philox"], ["mt", None]),
    "warmup": (["auto", True, False], ["yes", None]),
    "trial_range": ([None, (0, 1)], [(0, 0), (2, 1), (0, 99), "ab", 5]),
}


RUN_PLANTS = plants_of(RUN_SETTINGS)


def runner_case(data, plants):
    kwargs, faults = keyword_case(data, RUN_SETTINGS, plants)
    model = new_lg(1, 1)  # its own: the run moves it to its dtype
    filters = {"kf": F.KalmanFilter(model), "bpf": F.BootstrapParticleFilter(model, n_particles=4)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a tiny memory budget warns with the plan it made
        try:
            res = run_experiment(model, filters, progress=False, **kwargs)
        except TorchflowError as err:  # the runner's ConfigError among them
            assert faults, f"valid settings refused: {err!r}"
            assert any(k in str(err) for k in faults), f"{err!r} names none of {sorted(faults)}"
            return
    assert not faults, f"accepted {sorted(faults)}"
    assert not res.failures and all(row["error"] is None for row in res.summary), res.summary
    assert all(math.isfinite(v) for row in res.per_trial for v in row.values() if isinstance(v, float)), res.per_trial


@given(data=st.data())
@fuzz(30)
def test_the_runner_runs_valid_settings(data):
    runner_case(data, [])


@pytest.mark.parametrize("plant", RUN_PLANTS, ids=[f"{k}={v!r}" for k, v in RUN_PLANTS])
@given(data=st.data(), second=st.one_of(st.none(), st.sampled_from(RUN_PLANTS)))
@fuzz(3)
def test_the_runner_names_each_bad_setting(plant, data, second):
    runner_case(data, [plant] + ([second] if second is not None and second[0] != plant[0] else []))


# ---- found by the fuzz in the runner (torchflow/app/runner/plan.py) and fixed there: plain tests now ----


def _run(**kwargs):
    model = new_lg(1, 1)
    settings = {"trials": 2, "steps": 2, "progress": False, **kwargs}
    return run_experiment(model, {"kf": F.KalmanFilter(model)}, **settings)


def test_a_bad_run_setting_is_a_torchflow_error():
    with pytest.raises(TorchflowError, match="trials"):
        _run(trials=0)


@pytest.mark.parametrize("dtype", [torch.float16, torch.int64, torch.complex64])
def test_a_run_dtype_filters_cannot_use_is_named(dtype):
    with pytest.raises(TorchflowError, match="dtype"):
        _run(dtype=dtype)


def test_a_huge_memory_budget_runs():
    assert not _run(memory_budget_gb=1e300).failures
