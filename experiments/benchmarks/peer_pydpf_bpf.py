"""Bootstrap particle filter speed against the peer library PyDPF, in one process, on the same
device (the GPU goal: torchflow's BPF at least as fast as PyDPF's at every N from 200 to 1e5).

    python experiments/benchmarks/peer_pydpf_bpf.py --device cuda [--ns 200,1000,10000,100000]
        [--trials 100] [--steps 10] [--d 64] [--dtype float32] [--reps 3] [--out results_peer_pydpf_bpf.md]

Model: the linear-Gaussian sensor network (``SensorNetwork(d)``, Li & Coates' Table I setting:
``x_k = 0.9 x_{k-1} + v_k``, ``z_k = x_k + w_k``), observations simulated by torchflow, ``trials``
trials in one batched call, forward only (``torch.no_grad``).

Rows, each timed as the best of ``--reps`` calls after one warm-up call (``torch.cuda.synchronize``
around each):

* ``torchflow``: ``BootstrapParticleFilter`` with its defaults (systematic resampling when ESS < N/2),
  drawing from per-trial streams (``TrialStreams``, as the experiment runner does; on CUDA its step is
  then replayed from a CUDA graph up to ``tuning.graph_step_max_elems`` state elements:
  :mod:`torchflow.filters.graph_step`);
* ``torchflow, torch.Generator``: the same filter drawing from one ``torch.Generator`` for the batch
  (as PyDPF does): every step launched op by op;
* ``torchflow, resample always``: multinomial resampling at every step (``ess_threshold=1.0``), as
  PyDPF's ``ParticleFilter`` does (per-trial streams);
* ``PyDPF``: ``ParticleFilter(MultinomialResampler, FilteringModel(LinearGaussian, LinearGaussian))``
  with the filtering mean as its output (PyDPF 1.2.3). Its prior draws ``x_1 ~ N(0, Q)`` (the law of
  the first state given the known ``x_0 = 0``), so both filters process the same T observations.

``ratio``: PyDPF's seconds per trial-step over torchflow's (> 1: torchflow faster). PyDPF needs
Python >= 3.12; it imports polars and numpydoc at import time for its data-loading helpers, which
are not used here: where they are missing the script puts empty stand-ins in ``sys.modules`` first.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
import types
import warnings
from pathlib import Path

import torch


def _stub_missing(*names):
    """Empty stand-ins for modules PyDPF imports but this benchmark never uses."""
    for n in names:
        if n not in sys.modules and importlib.util.find_spec(n) is None:  # a stub already there has no spec
            m = types.ModuleType(n)

            def ga(attr):
                if attr.startswith("__"):
                    raise AttributeError(attr)
                return type(attr, (), {})

            m.__getattr__ = ga
            sys.modules[n] = m


def _time(fn, reps, device):
    fn()  # warm-up
    best = float("inf")
    for _ in range(reps):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - t0)
    return best


def pydpf_available() -> bool:
    """PyDPF is importable here (it needs Python >= 3.12)."""
    if sys.version_info < (3, 12) or importlib.util.find_spec("pydpf") is None:
        return False
    _stub_missing("polars", "numpydoc")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            importlib.import_module("pydpf")
    except Exception:  # a broken install is as good as none
        return False
    return True


def compare(
    device, ns, trials: int = 100, steps: int = 10, d: int = 64, dtype=torch.float32, reps: int = 3, log=print
) -> list:
    """One row per N: seconds per trial-step of ``torchflow`` (defaults), ``torchflow, resample always``
    and ``PyDPF`` (``None`` with ``PyDPF error`` when it fails, e.g. out of memory), on ``device``."""
    device = torch.device(device)
    if device.type == "cuda" and device.index is None:  # PyDPF compares devices with their index
        device = torch.device("cuda", torch.cuda.current_device())
    before = torch.get_default_dtype()
    torch.set_default_dtype(dtype)  # PyDPF's constants and draws use the default dtype
    try:
        return _compare(device, ns, trials, steps, d, dtype, reps, log)
    finally:
        torch.set_default_dtype(before)


def _compare(device, ns, trials, steps, d, dtype, reps, log):
    _stub_missing("polars", "numpydoc")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import pydpf
    from torchflow.core.random import TrialStreams
    from torchflow.filters import BootstrapParticleFilter
    from torchflow.models import SensorNetwork

    model = SensorNetwork(d=d).to(device=device, dtype=dtype)
    g = torch.Generator(device=device).manual_seed(0)
    traj = model.simulate(trials, steps, g)
    mean, cov = model.initial_belief(traj.states[:, 0], g)
    obs = traj.observations  # (B, T, m)
    F, Q, H, R = model.F, model.Q, model.H, model.R
    zero = torch.zeros(d, dtype=dtype, device=device)
    LQ, LR = torch.linalg.cholesky(Q), torch.linalg.cholesky(R)
    pg = torch.Generator(device=device).manual_seed(1)

    class Prior(pydpf.Module):  # x_1 ~ N(0, Q): the first state given x_0 = 0
        def sample(self, batch_size, n_particles, **data):
            v = torch.randn((batch_size, n_particles, d), generator=pg, dtype=dtype, device=device)
            return v @ LQ.T

        def log_density(self, state, **data):
            return torch.distributions.MultivariateNormal(zero, scale_tril=LQ).log_prob(state)

    ssm = pydpf.FilteringModel(
        dynamic_model=pydpf.LinearGaussian(weight=F, bias=zero, cholesky_covariance=LQ, generator=pg),
        observation_model=pydpf.LinearGaussian(weight=H, bias=zero.clone(), cholesky_covariance=LR, generator=pg),
        prior_model=Prior(),
    )
    peer = pydpf.ParticleFilter(pydpf.MultinomialResampler(generator=pg), ssm)
    obs_tb = obs.transpose(0, 1).contiguous()  # PyDPF is time-major (T, B, m)
    rows = []
    for n in ns:
        row = {"N": int(n)}
        for name, kw, gen in (
            ("torchflow", {}, "streams"),
            ("torchflow, torch.Generator", {}, "torch"),
            ("torchflow, resample always", dict(resampling="multinomial", ess_threshold=1.0), "streams"),
        ):
            f = BootstrapParticleFilter(model, n_particles=int(n), **kw)
            tg = (
                torch.Generator(device=device).manual_seed(2)
                if gen == "torch"
                else TrialStreams(2, trials, f.stream_name)
            )  # made once: calls continue the streams

            def ours(f=f, tg=tg):
                with torch.no_grad():
                    f(obs, mean, cov, tg)

            row[name] = _time(ours, reps, device) / (trials * steps)

        def theirs(n=int(n)):
            with torch.no_grad():
                peer(
                    n_particles=n, time_extent=steps - 1, aggregation_function=pydpf.FilteringMean(), observation=obs_tb
                )

        try:
            row["PyDPF"] = _time(theirs, reps, device) / (trials * steps)
        except RuntimeError as err:  # out of memory at the largest N, say
            row["PyDPF"], row["PyDPF error"] = None, str(err).splitlines()[0]
        rows.append(row)
        log(json.dumps(row))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--ns", default="200,1000,10000,100000")
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--d", type=int, default=64)
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    device = torch.device(a.device)
    rows = compare(
        device,
        [int(float(v)) for v in a.ns.split(",")],
        a.trials,
        a.steps,
        a.d,
        getattr(torch, a.dtype),
        a.reps,
        log=lambda line: print(line, flush=True),
    )
    import pydpf

    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    lines = [
        f"# Bootstrap PF: torchflow against PyDPF {getattr(pydpf, '__version__', '1.2.3')}",
        "",
        f"{name}, torch {torch.__version__}, {a.dtype}, SensorNetwork d = {a.d}, {a.trials} trials x {a.steps} steps "
        f"per call, best of {a.reps} after a warm-up; seconds per trial-step. ratio = PyDPF / torchflow (> 1: "
        "torchflow faster).",
        "",
        "| N | torchflow | torchflow, torch.Generator | torchflow, resample always | PyDPF | ratio (default) "
        "| ratio (torch.Generator) | ratio (resample always) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        p, t, tg, t1 = r["PyDPF"], r["torchflow"], r["torchflow, torch.Generator"], r["torchflow, resample always"]
        peer, ratio, ratio_g, ratio1 = (
            ("error", "-", "-", "-") if p is None else (f"{p:.3g}", f"{p / t:.2f}", f"{p / tg:.2f}", f"{p / t1:.2f}")
        )
        lines.append(f"| {r['N']} | {t:.3g} | {tg:.3g} | {t1:.3g} | {peer} | {ratio} | {ratio_g} | {ratio1} |")
    md = "\n".join(lines) + "\n"
    print(md)
    if a.out:
        Path(a.out).write_text(md)
        Path(a.out).with_suffix(".json").write_text(json.dumps(dict(rows=rows, args=vars(a), device=name), indent=1))


if __name__ == "__main__":
    main()
