"""The fused pseudo-step of EDH/LEDH at per-particle points (torchflow.flows.kernels.steps) against the torch
path: Triton's kernel on the CPU through its interpreter (a subprocess with TRITON_INTERPRET=1;
skipped where Triton is not installed) and on CUDA compiled; Numba's CPU kernel (skipped where
Numba is not installed)."""

import json
import os
import subprocess
import sys
import textwrap

import pytest
import torch
from conftest import ROOT, cuda

from torchflow.flows import select as S
from torchflow.flows.measurement import measurement_form


def _kernel(flow, meas, x, k):
    """The flow kernel the selection picks at per-particle points (no tracked law, no image)."""
    return S.flow_kernel(flow, meas, x, k, per_particle=True, track=False, gaussian_image=False)


CHECK = textwrap.dedent("""
    import json, sys
    import torch
    from torchflow.core import tuning
    from torchflow.flows import integrate_flow, FlowPrior, LEDHFlow, EDHFlow
    from torchflow.models import AcousticTracking, LinearGaussian
    from torchflow.flows.schedules import ExponentialSchedule
    from torchflow.flows import integrate as I
    from torchflow.flows.kernels import steps as fused
    from torchflow.flows import select as S

    device = sys.argv[1]
    fused.ROWS_WARPS = 1  # 32 particles per program
    if len(sys.argv) > 3:
        tuning.set(fused_info=int(sys.argv[3] == "info"))  # the GPU kernel's form: info or rows
    def case(model, B, N, dtype, shared_cov, flow, spread=0.0):
        g = torch.Generator().manual_seed(0)
        model = model.to(dtype=dtype)
        d = model.state_dim
        traj = model.simulate(B, 2, g)
        x = traj.states[:, 1].unsqueeze(1) + 0.3 * torch.randn(B, N, d, dtype=dtype, generator=g)
        A = 0.1 * torch.randn(B, 1 if shared_cov else N, d, d, dtype=dtype, generator=g)
        P = A @ A.transpose(-1, -2) + torch.eye(d, dtype=dtype)
        D = torch.logspace(0, -spread, d, dtype=dtype)  # spread: P's condition number ~ 10^(2 spread)
        P = D[:, None] * P * D[None, :]
        prior = FlowPrior((x + 0.1).to(device), torch.linalg.cholesky(P).to(device))
        model, x, z = model.to(device), x.to(device), traj.observations[:, 1].to(device)
        with torch.no_grad():
            meas = I.GaussianMeasurement.from_model(model, z)
            k = d if model.structure.measurement_support is None else len(model.structure.measurement_support)
            fusable = S.flow_kernel(flow, meas, x, k, per_particle=True, track=False, gaussian_image=False) == "lanes"
            inside = int(sys.argv[2])  # 1: the kernel linearises the model itself (acoustic)
            if inside:
                meas.prepare(x)
                fusable = fusable and S.measured_inside(meas, torch.arange(k), k) is not None
            with tuning.tuned(fused_flows=0):
                ref = integrate_flow(flow, model, x, z, prior, ExponentialSchedule(3, 1.2), points="particle")
            with tuning.tuned(fused_measurement=inside):
                out = integrate_flow(flow, model, x, z, prior, ExponentialSchedule(3, 1.2),
                                     points="particle")
        err = {k: ((getattr(out, k) - getattr(ref, k)).abs().max() / getattr(ref, k).abs().max().clamp_min(1)).item()
               for k in ("particles", "log_det", "aux")}
        return dict(fusable=fusable, **err)
    torch.manual_seed(0)
    H = torch.randn(2, 3, dtype=torch.float64)
    lg = lambda: LinearGaussian(0.9 * torch.eye(3, dtype=torch.float64), 0.5 * torch.eye(3, dtype=torch.float64), H,
                                0.2 * torch.eye(2, dtype=torch.float64))
    only_acoustic = int(sys.argv[2]) == 1
    res = {
        "acoustic": case(AcousticTracking(), 2, 3, torch.float64, False, LEDHFlow()),
        "acoustic shared P": case(AcousticTracking(), 2, 3, torch.float64, True, LEDHFlow()),
        "acoustic float32": case(AcousticTracking(), 2, 3, torch.float32, False, LEDHFlow()),
        "acoustic, P's condition ~1e6": case(AcousticTracking(), 2, 3, torch.float64, False, LEDHFlow(), spread=3.0),
        **({} if only_acoustic else {"linear, shared W, EDH at particles": case(lg(), 2, 3, torch.float64, False,
                                                                                  EDHFlow())}),
        "acoustic, 40 particles (two programs of 32)": case(AcousticTracking(), 2, 20, torch.float64, False,
        LEDHFlow()),
    }
    print("RESULT" + json.dumps(res))
""")


def _check(device, inside, env=None, layout=None):
    out = subprocess.run(
        [sys.executable, "-c", CHECK, device, str(inside)] + ([layout] if layout else []),
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, **(env or {})},
        timeout=600,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.split("RESULT")[-1])


def _assert_close(res, tol64, tol32):
    for name, r in res.items():
        assert r["fusable"], f"{name}: the fused path was not taken"
        tol = tol32 if "float32" in name else tol64
        for k in ("particles", "log_det", "aux"):
            assert r[k] < tol, f"{name}: {k} differs from the torch path by {r[k]:.2e} (relative)"


#: ``tuning.fused_measurement``: 0 the model's linearisation in torch, 1 inside the kernel (acoustic)
KERNELS = pytest.mark.parametrize("inside", [0, 1], ids=["measurement in torch", "measurement inside"])


#: the GPU kernel's two forms (``tuning.fused_info``)
LAYOUTS = pytest.mark.parametrize("layout", ["info", "rows"])


@pytest.mark.slow  # 60-75 s of one core in all (the Triton interpreter); the CPU kernels' twin stays in tier one
@LAYOUTS
@KERNELS
def test_fused_step_matches_torch_in_triton_interpreter(inside, layout):
    pytest.importorskip("triton")
    _assert_close(_check("cpu", inside, {"TRITON_INTERPRET": "1"}, layout), 1e-11, 1e-4)


F32_CHECK = textwrap.dedent("""
    import json, sys
    import torch
    from torchflow.core import tuning
    from torchflow.flows import integrate_flow, FlowPrior, LEDHFlow
    from torchflow.models import AcousticTracking
    from torchflow.flows.schedules import ExponentialSchedule

    def run(dtype, fused, kf32, B=2, N=3):
        g = torch.Generator().manual_seed(0)
        model = AcousticTracking()
        d = model.state_dim
        traj = model.simulate(B, 2, g)
        x = traj.states[:, 1].unsqueeze(1) + 0.3 * torch.randn(B, N, d, dtype=torch.float64, generator=g)
        A = 0.1 * torch.randn(B, N, d, d, dtype=torch.float64, generator=g)
        P = A @ A.transpose(-1, -2) + torch.eye(d, dtype=torch.float64)
        prior = FlowPrior((x + 0.1).to(dtype), torch.linalg.cholesky(P).to(dtype))
        model, x, z = model.to(dtype=dtype), x.to(dtype), traj.observations[:, 1].to(dtype)
        with torch.no_grad(), tuning.tuned(fused_flows=fused, kernel_float32=kf32, fused_measurement=1):
            return integrate_flow(LEDHFlow(), model, x, z, prior, ExponentialSchedule(3, 1.2), points="particle")

    ref = run(torch.float64, 0, 0)
    err = lambda o: max(((o.particles.double() - ref.particles).abs().max() / ref.particles.abs().max()).item(),
                        ((o.aux.double() - ref.aux).abs().max() / ref.aux.abs().max()).item())
    print("RESULT" + json.dumps({"f32": err(run(torch.float32, 1, 1)), "f64": err(run(torch.float32, 1, 0)),
                                 "torch": err(run(torch.float32, 0, 0))}))
""")


def test_float32_arithmetic_in_the_gpu_kernel():
    """``tuning.kernel_float32=1``: the GPU lane kernel (Triton's interpreter) computes a float32
    run in float32. Measured against the float64 flow: 1.5e-4 relative (the information form's
    ``Pi + lam G`` at acoustic tracking's sharp measurement), against 8.7e-7 for the kernel in
    float64 arithmetic (the default) and 1.3e-7 for the torch path in float32. The bounds: within
    1e-3, and above 1e-5 (so float32 arithmetic did run: float64 arithmetic stays 10x below)."""
    pytest.importorskip("triton")
    out = subprocess.run(
        [sys.executable, "-c", F32_CHECK],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, "TRITON_INTERPRET": "1"},
        timeout=600,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    err = json.loads(out.stdout.split("RESULT")[-1])
    assert 1e-5 < err["f32"] < 1e-3 and err["f64"] < 1e-5 and err["torch"] < 1e-5, err


@KERNELS
def test_fused_step_matches_torch_with_numba_on_cpu(inside):
    """The CPU kernel (torchflow.flows.kernels.cpu, Numba): blocks of 64 particle lanes, here 6 and
    40 particles (one partly filled group of lanes)."""
    pytest.importorskip("numba")
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    out = subprocess.run(
        [sys.executable, "-c", CHECK, "cpu", str(inside)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env=env,
        timeout=600,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    _assert_close(json.loads(out.stdout.split("RESULT")[-1]), 1e-11, 1e-4)


def test_cpu_kernel_gives_the_same_bits_on_any_thread_count_and_split():
    """Particles do not interact in the CPU kernel: 1 or 2 threads, and 130 particles flowed at once
    or as 64 + 66 (other lanes and blocks), give the same bits."""
    pytest.importorskip("numba")
    from torchflow.flows import FlowPrior, LEDHFlow, integrate_flow
    from torchflow.flows.schedules import ExponentialSchedule
    from torchflow.models import AcousticTracking

    model = AcousticTracking()
    g = torch.Generator().manual_seed(3)
    traj = model.simulate(2, 2, g)
    x = traj.states[:, 1].unsqueeze(1) + 0.3 * torch.randn(2, 65, 16, dtype=torch.float64, generator=g)
    A = 0.1 * torch.randn(2, 65, 16, 16, dtype=torch.float64, generator=g)
    L = torch.linalg.cholesky(A @ A.transpose(-1, -2) + torch.eye(16, dtype=torch.float64))
    z = traj.observations[:, 1]

    def flow(sl, threads):
        n = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            with torch.no_grad():
                out = integrate_flow(
                    LEDHFlow(),
                    model,
                    x[:, sl],
                    z,
                    FlowPrior(x[:, sl] + 0.1, L[:, sl]),
                    ExponentialSchedule(4, 1.2),
                    points="particle",
                )
        finally:
            torch.set_num_threads(n)
        return out.particles, out.log_det

    whole = flow(slice(None), 2)
    for got in (
        flow(slice(None), 1),
        tuple(torch.cat(p, 1) for p in zip(flow(slice(0, 32), 2), flow(slice(32, None), 1))),
    ):
        assert all(torch.equal(a, b) for a, b in zip(got, whole))


@pytest.mark.parametrize("inside", [0, 1], ids=["measurement in torch", "measurement inside"])
@pytest.mark.parametrize("tracked", [True, False], ids=["tracked law", "no law"])
def test_fused_gromov_step_matches_torch_on_cpu(inside, tracked):
    """The Gromov flow's CPU kernel (torchflow.flows.kernels.cpu.gromov_step): the same draws, the
    particles, points and tracked Gaussian law (mean, covariance, log-density) of the torch path to
    round-off, for 2 x 70 particles (a partly filled group of 64 lanes) with per-particle priors."""
    pytest.importorskip("numba")
    from torchflow.core import tuning
    from torchflow.flows import FlowPrior, GromovFlow, integrate_flow
    from torchflow.flows import integrate as I
    from torchflow.models import AcousticTracking

    m = AcousticTracking()
    g = torch.Generator().manual_seed(0)
    B, N, d = 2, 70, 16
    traj = m.simulate(B, 2, g)
    x = traj.states[:, 1].unsqueeze(1) + 0.3 * torch.randn(B, N, d, dtype=torch.float64, generator=g)
    A = 0.3 * torch.randn(B, N, d, d, dtype=torch.float64, generator=g)
    L = torch.linalg.cholesky(A @ A.transpose(-1, -2) + 0.5 * torch.eye(d, dtype=torch.float64))
    law = FlowPrior(x - 0.05, torch.linalg.cholesky(0.1 * torch.eye(d, dtype=torch.float64))) if tracked else None
    outs = []
    for fz in (0, 1):
        with tuning.tuned(fused_flows=fz, fused_measurement=inside), torch.no_grad():
            meas = I.GaussianMeasurement.from_model(m, traj.observations[:, 1])
            assert (_kernel(GromovFlow(), meas, x, 8) == "gromov") == bool(fz)
            outs.append(
                integrate_flow(
                    GromovFlow(),
                    m,
                    x,
                    traj.observations[:, 1],
                    FlowPrior(x + 0.1, L),
                    None,
                    points="particle",
                    proposal=law,
                    generator=torch.Generator().manual_seed(4),
                )
            )
    keys = ("particles", "aux") + (("log_proposal", "proposal_mean", "proposal_cov") if tracked else ())
    for k in keys:
        a, b = getattr(outs[0], k), getattr(outs[1], k)
        assert not torch.equal(a, b) or k == "aux"  # another computation
        assert ((a - b).abs().max() / a.abs().max()).item() < 1e-11, k


def _gpfis_case(model, B, N, per_particle_cov, dtype=torch.float64, seed=0):
    """GPFIS's inputs: particles drawn from the transition of jittered states, its prior (per-particle
    means; the model's shared factor, or per-particle factors), the observation."""
    from torchflow.flows import FlowPrior

    g = torch.Generator().manual_seed(seed)
    model = model.to(dtype=dtype)
    d = model.state_dim
    traj = model.simulate(B, 2, g)
    xp = traj.states[:, 1].unsqueeze(1) + 0.3 * torch.randn(B, N, d, dtype=dtype, generator=g)
    x0 = model.sample_transition(xp, g)
    L = model.transition_scale_tril(xp)
    if per_particle_cov:
        A = 0.3 * torch.randn(B, N, d, d, dtype=dtype, generator=g)
        L = torch.linalg.cholesky(A @ A.transpose(-1, -2) + L @ L.transpose(-1, -2))
    return model, x0, FlowPrior(model.transition_mean(xp), L), traj.observations[:, 1]


def _gpfis(model, x0, prior, z, steps=5, **tuned):
    from torchflow.core import tuning
    from torchflow.flows import GaussianMeasurement
    from torchflow.flows.gpfis import gpfis_flow
    from torchflow.flows.schedules import ExponentialSchedule

    with tuning.tuned(**tuned), torch.no_grad():
        return gpfis_flow(GaussianMeasurement.from_model(model, z), x0, prior, ExponentialSchedule(steps, 1.2))


@pytest.mark.parametrize("inside", [0, 1], ids=["measurement in torch", "measurement inside"])
@pytest.mark.parametrize("case", ["shared factor", "per-particle factors", "float32", "linear"])
def test_fused_gpfis_matches_torch_on_cpu(inside, case):
    """GPFIS's CPU kernel (torchflow.flows.kernels.cpu.gpfis_step): the moved particles and the
    accumulated log|det| of the torch path's analytic Jacobian to round-off, for 2 x 70 particles
    (a partly filled group of 64 lanes): acoustic with the model's shared transition factor or
    per-particle factors, in float32, and a linear-Gaussian model (second derivatives zero)."""
    pytest.importorskip("numba")
    from torchflow.flows import FlowPrior, GaussianMeasurement
    from torchflow.models import AcousticTracking, LinearGaussian

    if case == "linear":
        if inside:
            pytest.skip("the kernel linearises only the acoustic measurement itself")
        gen = torch.Generator().manual_seed(1)
        e = torch.eye(3, dtype=torch.float64)
        model = LinearGaussian(0.9 * e, 0.5 * e, torch.randn(2, 3, dtype=torch.float64, generator=gen), 0.2 * e[:2, :2])
    else:
        model = AcousticTracking()
    dtype = torch.float32 if case == "float32" else torch.float64
    model, x0, prior, z = _gpfis_case(model, 2, 70, case == "per-particle factors", dtype)
    with torch.no_grad():
        k = 8 if case != "linear" else 3
        assert S.gpfis_kernel(GaussianMeasurement.from_model(model, z), x0, k)
    out = _gpfis(model, x0, prior, z, fused_flows=1, fused_measurement=inside)
    if dtype == torch.float32:  # the kernel computes in float64: against the torch path in float64
        # (the torch path in float32 is 3e-3 off in the particles and 7e-2 in log|det| here; the
        # kernel 3e-5 when torch linearises in float32, 3e-6 when it linearises itself)
        ref = _gpfis(
            model.to(dtype=torch.float64),
            x0.double(),
            FlowPrior(prior.mean.double(), prior.scale_tril.double()),
            z.double(),
            fused_flows=0,
        )
        tol = 1e-4
    else:
        ref = _gpfis(model, x0, prior, z, fused_flows=0)
        # a particle of the per-particle case has an ill-conditioned step: there the torch path's own
        # analytic and autodiff Jacobians differ by 4e-10 relative in log|det| (the kernel by 3e-10)
        tol = 1e-9
    for a, b, name in zip(ref, out, ("particles", "log_det")):
        assert b.dtype == dtype and a.shape == b.shape
        if case != "linear":
            assert not torch.equal(a.to(dtype), b), name  # another computation
        assert ((a - b.to(a.dtype)).abs().max() / a.abs().max()).item() < tol, name


def test_fused_gpfis_gives_the_same_bits_on_any_thread_count_and_split():
    """GPFIS's CPU kernel: 1 or 2 threads, 130 particles at once or as 32 + 98, the same bits."""
    pytest.importorskip("numba")
    from torchflow.flows import FlowPrior
    from torchflow.models import AcousticTracking

    model, x0, prior, z = _gpfis_case(AcousticTracking(), 2, 130, False, seed=3)

    def run(sl, threads):
        n = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            return _gpfis(model, x0[:, sl], FlowPrior(prior.mean[:, sl], prior.scale_tril), z, steps=4)
        finally:
            torch.set_num_threads(n)

    whole = run(slice(None), 2)
    for got in (
        run(slice(None), 1),
        tuple(torch.cat(p, 1) for p in zip(run(slice(0, 32), 2), run(slice(32, None), 1))),
    ):
        assert all(torch.equal(a, b) for a, b in zip(got, whole))


def test_fused_gpfis_only_where_it_applies(monkeypatch):
    """The torch path runs with a gradient recorded, ``fused_flows=0``, without Numba, or without
    declared second derivatives (a state-dependent R); the autodiff Jacobian and the symmetric root
    never reach the kernel."""
    from torchflow.core import tuning
    from torchflow.flows import GaussianMeasurement
    from torchflow.flows import gpfis as GP
    from torchflow.flows.kernels import steps as fused
    from torchflow.models import AcousticTracking

    model, x0, prior, z = _gpfis_case(AcousticTracking(), 1, 4, False)
    meas = GaussianMeasurement.from_model(model, z)
    monkeypatch.setattr(fused, "_numba", True)
    assert not S.gpfis_kernel(meas, x0, 8)  # a gradient is recorded
    with torch.no_grad():
        assert S.gpfis_kernel(meas, x0, 8)
        with tuning.tuned(fused_flows=0):
            assert not S.gpfis_kernel(meas, x0, 8)
        assert not S.gpfis_kernel(meas, x0, 17)  # k > 16: the kernel's per-lane second derivatives grow as k^3
        meas.hessian = None
        assert not S.gpfis_kernel(meas, x0, 8)
        monkeypatch.setattr(fused, "_numba", False)
        assert not S.gpfis_kernel(GaussianMeasurement.from_model(model, z), x0, 8)
    monkeypatch.setattr(GP, "_fused_flow", lambda *a: (_ for _ in ()).throw(AssertionError("fused")))
    monkeypatch.setattr(fused, "_numba", True)
    for root, jac in (("symmetric", "analytic"), ("cholesky", "autodiff")):
        with torch.no_grad():
            GP.gpfis_flow(GaussianMeasurement.from_model(model, z), x0, prior, None, root, jac)


def _diag_case(d, B, N, shared, dtype=torch.float64, seed=0):
    """A diagonal measurement (skewed-t / Poisson, d = 64: too large for the lane kernel's tiles),
    per-particle points near the truth, a prior shared by the particles of a trial (as a
    Gaussian-sum component's) or one per particle (as PF-PF(LEDH)'s)."""
    from torchflow.flows import FlowPrior
    from torchflow.models import SkewedTPoisson

    g = torch.Generator().manual_seed(seed)
    model = SkewedTPoisson(d=d).to(dtype=dtype)
    traj = model.simulate(B, 2, g)
    x = traj.states[:, 1].unsqueeze(1) + 0.3 * torch.randn(B, N, d, dtype=dtype, generator=g)
    A = 0.1 * torch.randn(B, 1 if shared else N, d, d, dtype=dtype, generator=g)
    P = A @ A.transpose(-1, -2) + 0.5 * torch.eye(d, dtype=dtype)
    prior = FlowPrior(x.mean(1, keepdim=True).expand(B, N, d) + 0.1, torch.linalg.cholesky(P))
    return model, x, prior, traj.observations[:, 1]


def _flow(model, x, prior, z, flow=None, **tuned):
    from torchflow.core import tuning
    from torchflow.flows import LEDHFlow, integrate_flow

    with tuning.tuned(**tuned), torch.no_grad():
        return integrate_flow(flow or LEDHFlow(), model, x, z, prior, None, points="particle")


@pytest.mark.parametrize("case", ["shared prior", "per-particle priors", "float32", "EDH at the particles"])
def test_fused_diagonal_step_matches_torch_on_cpu(case):
    """The information-form CPU kernel for a diagonal W (torchflow.flows.kernels.cpu.dh_diag_step):
    the particles, points and log|det| of the torch path (covariance form) to round-off, for 2 x 30
    particles of the skewed-t / Poisson model at d = 64."""
    pytest.importorskip("numba")
    from torchflow.flows import EDHFlow, GaussianMeasurement, LEDHFlow

    dtype = torch.float32 if case == "float32" else torch.float64
    model, x, prior, z = _diag_case(64, 2, 30, case != "per-particle priors", dtype)
    flow = EDHFlow() if case.startswith("EDH") else LEDHFlow()
    with torch.no_grad():
        meas = GaussianMeasurement.from_model(model, z)
        assert _kernel(flow, meas, x, 64) == "diagonal"
    ref = _flow(model, x, prior, z, flow, fused_flows=0)
    out = _flow(model, x, prior, z, flow, fused_flows=1)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    for k in ("particles", "log_det", "aux"):
        a, b = getattr(ref, k), getattr(out, k)
        assert b.dtype == dtype and a.shape == b.shape
        if dtype == torch.float64:
            assert not torch.equal(a, b), k  # another computation
        assert ((a - b).abs().max() / a.abs().max()).item() < tol, k


def test_fused_diagonal_step_gives_the_same_bits_on_any_thread_count_and_split():
    pytest.importorskip("numba")
    from torchflow.flows import FlowPrior

    model, x, prior, z = _diag_case(64, 1, 40, False, seed=2)

    def run(sl, threads):
        n = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            out = _flow(model, x[:, sl], FlowPrior(prior.mean[:, sl], prior.scale_tril[:, sl]), z)
        finally:
            torch.set_num_threads(n)
        return out.particles, out.log_det

    whole = run(slice(None), 2)
    for got in (run(slice(None), 1), tuple(torch.cat(p, 1) for p in zip(run(slice(0, 7), 2), run(slice(7, None), 1)))):
        assert all(torch.equal(a, b) for a, b in zip(got, whole))


def test_gaussian_sum_flows_all_particles_at_once_with_the_diagonal_kernel():
    """With the diagonal CPU kernel no ``d x d`` matrix per particle is built, so the Gaussian-sum
    filter does not cut its particles into cache-sized blocks; on the torch path it does."""
    pytest.importorskip("numba")
    from torchflow.core import tuning
    from torchflow.filters import ParticleFlowGaussianSumParticleFilter
    from torchflow.flows import LEDHFlow, which_kernel
    from torchflow.models import AcousticTracking, SkewedTPoisson

    model = SkewedTPoisson(d=144)
    f = ParticleFlowGaussianSumParticleFilter(model, n_components=5, particles_per_component=200)
    assert (which_kernel(f.flow, model, "cpu") == "diagonal") and f.flow_chunk("cpu") is None
    assert not (which_kernel(f.flow, model, "meta") == "diagonal")
    assert not (which_kernel(LEDHFlow(), AcousticTracking(), "cpu") == "diagonal")  # W not diagonal
    assert not (which_kernel(LEDHFlow(), SkewedTPoisson(d=16), "cpu") == "diagonal")  # the lane kernel's size
    with tuning.tuned(fused_flows=0):
        assert not (which_kernel(f.flow, model, "cpu") == "diagonal") and f.flow_chunk("cpu") == 50


def test_cpu_precision_from_factor():
    """The diagonal kernel's ``P^{-1}`` from ``L``: torch's ``cholesky_inverse`` to round-off, the same
    bits on 1 or 2 threads (torch's batched one differs between them)."""
    pytest.importorskip("numba")
    import numba
    import numpy as np

    from torchflow.flows.kernels.cpu import precision_from_factor

    g = torch.Generator().manual_seed(0)
    A = torch.randn(2, 5, 33, 33, dtype=torch.float64, generator=g)
    L = torch.linalg.cholesky(A @ A.transpose(-1, -2) / 33 + torch.eye(33, dtype=torch.float64))
    outs = []
    for threads in (1, 2):
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
        out = np.empty((2, 5, 33, 33))
        precision_from_factor(L.numpy(), out)
        outs.append(torch.from_numpy(out))
    ref = torch.cholesky_inverse(L)
    assert ((outs[0] - ref).abs().max() / ref.abs().max()).item() < 1e-13
    assert torch.equal(outs[0], outs[1]) and torch.equal(outs[0], outs[0].transpose(-1, -2))


def test_diagonal_rows_are_the_linearisation_diagonal():
    """``GaussianMeasurement.at_diagonal`` (the model's elementwise forms) gives W's diagonal and y of
    ``at`` bit for bit; the base model's default (diagonals of the dense forms) too; measurements
    that are not diagonal give ``None``."""
    from torchflow.flows import GaussianMeasurement
    from torchflow.models import AcousticTracking, SkewedTPoisson
    from torchflow.models.base import GaussianStateSpaceModel

    model, x, _, z = _diag_case(16, 2, 5, True)
    meas = GaussianMeasurement.from_model(model, z)
    lin = meas.at(x)
    for rows in (
        meas.at_diagonal(x),
        GaussianMeasurement(
            z,
            model.linearize_measurement,
            model.measurement_scale_tril,
            "diagonal",
            diagonal=True,
            diagonal_rows=lambda p: GaussianStateSpaceModel.linearize_measurement_diagonal(model, p),
        ).at_diagonal(x),
    ):
        assert torch.equal(rows[0], lin.diag) and torch.equal(rows[1], lin.y)
    assert isinstance(model, SkewedTPoisson)
    acoustic = AcousticTracking()
    assert (
        GaussianMeasurement.from_model(acoustic, torch.zeros(1, 25, dtype=torch.float64)).at_diagonal(
            torch.zeros(1, 3, 16, dtype=torch.float64)
        )
        is None
    )


def test_not_fused_without_a_kernel_on_cpu(monkeypatch):
    """On the CPU without Numba (and without Triton's interpreter) the torch path runs."""
    from torchflow.flows import GromovFlow, LEDHFlow
    from torchflow.flows import integrate as I
    from torchflow.flows.kernels import steps as fused
    from torchflow.models import AcousticTracking

    monkeypatch.setattr(fused, "_numba", False)
    m = AcousticTracking()
    meas = I.GaussianMeasurement.from_model(m, torch.zeros(1, 25, dtype=torch.float64))
    with torch.no_grad():
        assert not _kernel(LEDHFlow(), meas, torch.zeros(1, 4, 16, dtype=torch.float64), 8) == "lanes"
        assert not _kernel(GromovFlow(), meas, torch.zeros(1, 4, 16, dtype=torch.float64), 8) == "gromov"
        assert not _kernel(GromovFlow(noise_root="symmetric"), meas, torch.zeros(1, 4, 16), 8) == "gromov"
        from torchflow.models import SkewedTPoisson

        poisson = I.GaussianMeasurement.from_model(SkewedTPoisson(d=64), torch.zeros(1, 64, dtype=torch.float64))
        assert not _kernel(LEDHFlow(), poisson, torch.zeros(1, 4, 64, dtype=torch.float64), 64) == "diagonal"
    monkeypatch.setattr(fused, "_numba", True)
    with torch.no_grad():
        assert _kernel(LEDHFlow(), poisson, torch.zeros(1, 4, 64, dtype=torch.float64), 64) == "diagonal"
        assert (
            not _kernel(LEDHFlow(), meas, torch.zeros(1, 4, 16, dtype=torch.float64), 64) == "diagonal"
        )  # W not diagonal
        assert not _kernel(GromovFlow(), poisson, torch.zeros(1, 4, 64, dtype=torch.float64), 64) == "diagonal"
    assert not _kernel(LEDHFlow(), poisson, torch.zeros(1, 4, 64, dtype=torch.float64), 64) == "diagonal"  # a gradient
    with torch.no_grad():
        assert _kernel(LEDHFlow(), meas, torch.zeros(1, 4, 16, dtype=torch.float64), 8) == "lanes"
    assert (
        not _kernel(LEDHFlow(), meas, torch.zeros(1, 4, 16, dtype=torch.float64), 8) == "lanes"
    )  # a gradient is recorded


@cuda
@LAYOUTS
@KERNELS
def test_fused_step_matches_torch_on_cuda(inside, layout):
    pytest.importorskip("triton")
    _assert_close(_check("cuda", inside, layout=layout), 1e-11, 1e-4)


@LAYOUTS
@pytest.mark.parametrize("inside", [0, 1], ids=["W read", "measurement inside"])
def test_fused_kernel_keeps_each_particle_in_one_thread_on_sm90(inside, layout):
    """Compiled for an H100 without one (Triton's compiler and ptxas): no warp shuffles (every
    reduction over a particle's k x k matrices stays in its thread) and spills under 4 KB per thread.
    The kernel's first version, with its ``[k, particles]`` tiles spread over threads by Triton's
    coalescing, made 1,728 shuffles and spilled 17.7 KB; the row form now 1.6-1.8 KB, the
    information form 2.6-2.7 KB (2026-11-26, ``results_kernel_registers.txt``): a bound a little
    above each catches a regression."""
    pytest.importorskip("triton")
    sys.path.insert(0, str(ROOT))
    from experiments.benchmarks.kernel_registers import measure

    r = measure(lin=inside, warps=1, arch=90, layout=layout)
    assert r["shuffles"] == 0, r
    bound = {"rows": 2200, "info": 3000}[layout]  # bytes; measured 1.6-1.8 KB and 2.6-2.7 KB with Triton 3.6
    assert r["spill_stores"] < bound and r["registers"] <= 255, r


def test_which_measurements_the_kernel_linearises_itself():
    """Only a model that declares its measurement in the kernel's terms (acoustic tracking, not a
    subclass that changes it), with its scalar R prepared and ``tuning.fused_measurement`` on."""
    from torchflow.core import tuning
    from torchflow.flows import integrate as I
    from torchflow.models import AcousticTracking, LinearGaussian

    class Moved(AcousticTracking):  # another measurement: the kernel must not compute the parent's
        def measure(self, x):
            return super().measure(x) + 1.0

    z = torch.zeros(2, 25, dtype=torch.float64)
    x = torch.zeros(2, 3, 16, dtype=torch.float64)
    sup = torch.tensor(AcousticTracking().structure.measurement_support)
    meas = I.GaussianMeasurement.from_model(AcousticTracking(), z)
    assert S.measured_inside(meas, sup, 8) is None  # not prepared: no 1 / sigma yet
    meas.prepare(x)
    assert S.measured_inside(meas, sup, 8).kind == 1
    with tuning.tuned(fused_measurement=0):
        assert S.measured_inside(meas, sup, 8) is None
    assert S.measured_inside(meas, None, 8) is None  # no declared support
    assert measurement_form(Moved()) is None and measurement_form(AcousticTracking())[0] == "inverse_distance_sum"
    lg = LinearGaussian(
        torch.eye(2, dtype=torch.float64),
        torch.eye(2, dtype=torch.float64),
        torch.eye(2, dtype=torch.float64),
        torch.eye(2, dtype=torch.float64),
    )
    assert I.GaussianMeasurement.from_model(lg, torch.zeros(1, 2, dtype=torch.float64)).form is None


def test_gpu_tiles_bounded_by_the_register_budget():
    """On a GPU the lane kernel holds a particle's k x k matrices in registers: acoustic tracking's
    tiles (k = 8, m = 25, d = 16) fit, k = 16 (the skewed-t model at d = 16) takes the torch path;
    the CPU's cache-sized bound is larger."""
    from torchflow.flows.select import tiles_fit

    assert tiles_fit(25, 8, 16, "cuda") and tiles_fit(2, 3, 3, "cuda")
    assert not tiles_fit(16, 16, 16, "cuda") and tiles_fit(16, 16, 16, "cpu")
    assert not tiles_fit(144, 144, 144, "cpu")


def test_info_factors_are_the_prior_precision_and_c():
    """The information-form kernel's factors (``fused.info_factors``): ``C = L L_s^{-1}`` (so
    ``C L_s = L``, and C's rows at the support are the identity when ``L``'s are ``L_s``) and
    ``P_s^{-1}`` (``P_s^{-1} L_s L_s^T = I``), float64 from float32 inputs, broadcasting a shared
    covariance's ``(B, 1, ...)`` against per-particle ones."""
    from torchflow.flows.kernels import steps as fused

    g = torch.Generator().manual_seed(0)
    A = torch.randn(2, 3, 6, 6, dtype=torch.float64, generator=g)
    root = torch.linalg.cholesky(A @ A.transpose(-1, -2) + torch.eye(6, dtype=torch.float64))
    L, Ls = root[..., :4], root[..., :4, :4]  # support = the first 4 coordinates
    C, Pi = fused.info_factors(L.to(torch.float32), Ls.to(torch.float32))
    assert C.dtype == Pi.dtype == torch.float64 and C.shape == (2, 3, 6, 4) and Pi.shape == (2, 3, 4, 4)
    assert torch.allclose(C @ Ls, L, atol=1e-5)
    assert torch.allclose(C[..., :4, :], torch.eye(4, dtype=torch.float64).expand(2, 3, 4, 4), atol=1e-5)
    assert torch.allclose(
        Pi @ (Ls @ Ls.transpose(-1, -2)), torch.eye(4, dtype=torch.float64).expand(2, 3, 4, 4), atol=1e-4
    )
    C1, Pi1 = fused.info_factors(L[:, :1], Ls)  # one L for all particles, per-particle L_s
    assert C1.shape == (2, 3, 6, 4) and torch.allclose(C1 @ Ls, L[:, :1].expand(2, 3, 6, 4), atol=1e-12)


def test_kernel_form_follows_tuning():
    """``tuning.fused_info`` picks the GPU kernel's form (information form by default), and
    ``tuning.kernel_float32`` its arithmetic (float64 by default)."""
    from torchflow.core import tuning

    assert S.gpu_form() == "info" and not S.gpu_float32()
    with tuning.tuned(fused_info=0, kernel_float32=1):
        assert S.gpu_form() == "rows" and S.gpu_float32()


def test_the_cpu_kernels_leave_torch_s_thread_count_alone():
    """Numba's OpenMP threading layer, started by the first kernel launch, used to set the process's
    OpenMP thread count to NUMBA_NUM_THREADS, torch's included (1 -> 2): timings taken "with one
    thread" ran two. The kernels start it first and put torch's count back (a fresh process: the
    layer starts once per process)."""
    pytest.importorskip("numba")
    code = textwrap.dedent("""
        import torch
        torch.set_num_threads(1)
        from torchflow.models import SkewedTPoisson
        from torchflow.filters import ParticleFlowParticleFilter
        m = SkewedTPoisson(d=9)
        traj = m.simulate(2, 2, torch.Generator().manual_seed(0))
        mean, cov = m.initial_belief(traj.states[:, 0])
        with torch.no_grad():
            r = ParticleFlowParticleFilter(m, n_particles=16)(traj.observations, mean, cov,
            torch.Generator().manual_seed(1))
        print("RESULT", torch.get_num_threads(), sorted(r.paths))
    """)
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "TRITON_INTERPRET")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    threads, paths = out.stdout.split("RESULT")[-1].split(maxsplit=1)
    assert "kernel" in paths and int(threads) == 1, out.stdout
