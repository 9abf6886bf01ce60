"""The smoothing and parameter-posterior tasks of the ``torchflow`` command: ``task=smooth`` and
``task=pmmh`` (``task=filter``, the default, runs and scores the filters: :mod:`torchflow.app.cli`).

    torchflow task=smooth model=linear_gaussian model.d=4 'filter=[kf,bpf]'     # RTS beside FFBSi
    torchflow experiment=smooth_acoustic smooth.method=genealogy
    torchflow experiment=pmmh_stochastic_volatility pmmh.iterations=2000
    torchflow experiment=pmmh_stochastic_volatility data=returns.csv            # recorded returns

Both tasks build the model and the selected filters from the same configs as the filter task, run in
the same command shell (unknown keys, the output folder's guard, device, dtype, threads, signals:
:mod:`torchflow.app.runner.shell`) and take their data the same way: simulated from the model config
(``trials``, ``steps``, ``seed``), or recorded (``data=<file>``: no truth).

``task=smooth`` (:func:`smooth_job`) filters every trial with each selected filter and smooths it
with :func:`torchflow.smoothing.smooth` (``smooth.method``: ``auto``, ``rts``, ``ffbsi``,
``genealogy``; ``smooth.n_paths``; ``smooth.path_chunk``), each trial with its own random stream.
It writes ``smoothed.csv`` (one row per filter, trial and step 0..T: the true state where simulated,
the filtered and the smoothed mean and standard deviation of each coordinate), ``smoothing.json``
(per filter: the method, the RMSE of the filtered and of the smoothed means against the truth, the
mean over trials with its standard error, their paired difference, the seconds) and
``smoothed.png`` (trial 0: the truth, the filtered and smoothed means with +-2 sd bands).

``task=pmmh`` (:func:`pmmh_job`) samples the posterior of the parameters named in ``pmmh.priors``
by particle marginal Metropolis-Hastings (:func:`torchflow.inference.pmmh`), each selected filter
being the likelihood estimator of its own run, on one series: trial 0 of a simulation (the model
config's values are then the truth) or the recorded series of ``data=``. Priors are written as

    pmmh:
      priors:
        rho: {dist: Uniform, low: -1.0, high: 1.0}     # any torch.distributions class and its arguments
        sigma: {dist: Gamma, concentration: 1.0, rate: 1.0}

(:func:`prior_from_config`); the parameters must be per-trial parameters of the model
(:attr:`~torchflow.models.StateSpaceModel.per_trial_parameters`). The filters start each chain from
the model's declared prior at the chain's parameter values (the stationary law of stochastic
volatility), or, for a model without one, from the simulation's prior of trial 0. It writes
``posterior.csv`` (one row per filter, chain and kept iteration: the log-likelihood estimate and
each parameter), ``pmmh.json`` (per filter and parameter: posterior mean, sd, Monte Carlo standard
error ``sd / sqrt(ESS)``, split R-hat, ESS, ESS per second, the truth where simulated; the acceptance
rate and random-walk scale per chain; the seconds), and ``posterior.png`` (histograms) and
``traces.png`` (trace plots) per parameter.

Refused before anything runs (one line naming the key, what it expects and what it got, exit 2): an
unknown ``task``; a smoother that does not fit a filter (``smooth.method=rts`` with a particle filter,
``ffbsi`` with the Kalman family, any smoother with an ensemble or Gaussian-sum filter); a prior for
a parameter the model does not declare per trial, an unknown distribution or bad arguments; a
filter whose log-evidence is no likelihood estimate (the EKF, UKF, ensemble, Gaussian-sum and
unweighted flow filters; the Kalman filter on a linear-Gaussian model is exact and accepted);
``resume``, ``trial_range`` and ``torchrun`` (filter task only). A stop request (Ctrl-C, SIGTERM)
ends ``task=smooth`` after the filter that runs (the finished filters' results are written) and
``task=pmmh`` at once (nothing is written: a chain cut short is no sample).
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Dict, List, Mapping, Optional

import torch
from omegaconf import DictConfig, OmegaConf

from torchflow.app.runner import STOP, RunStopped, figures, format_table, plan_run, shell, writers
from torchflow.app.runner import config as rc
from torchflow.app.runner.plan import ConfigError, require
from torchflow.core import metrics
from torchflow.core.errors import ArgumentError
from torchflow.core.random import TrialStreams
from torchflow.models.trials import parameter_domain, support_within

log = logging.getLogger("torchflow.app.tasks")

#: the tasks of the ``torchflow`` command
TASKS = ("filter", "smooth", "pmmh")


def check_task(cfg: Mapping) -> str:
    """The config's ``task`` (:data:`TASKS`); for ``smooth`` and ``pmmh`` the settings only the filter
    task has are refused (``resume``, ``trial_range``, a ``torchrun`` start)."""
    task = cfg.get("task", "filter")
    require(task in TASKS, "task", f"one of {', '.join(TASKS)}", task)
    if task != "filter":
        require(
            not cfg.get("resume", False),
            "resume",
            f"false with task={task} (only task=filter saves chunks)",
            cfg.get("resume"),
        )
        require(
            cfg.get("trial_range") is None,
            "trial_range",
            f"null with task={task} (every trial runs)",
            cfg.get("trial_range"),
        )
        world = int(os.environ.get("WORLD_SIZE", "1") or 1)
        require(world == 1, "task", f"filter under torchrun (task={task} runs in one process)", task)
    return task


def _data(cfg: DictConfig, model, filters, env, one_series: bool = False):
    """The run's data through the runner (:func:`~torchflow.app.runner.plan_run`): simulated from the
    model config, or ``data=``; ``(plan, recorded data sha256 or None)``. ``one_series``: one trial
    (a recorded file of several series is refused)."""
    data = rc.recorded_data(cfg, model)
    obs, n, steps, sha = (
        (data.observations, data.trials, data.steps, data.sha256)
        if data is not None
        else (None, cfg.trials, cfg.steps, None)
    )
    if one_series:
        require(
            obs is None or obs.dim() == 2 or obs.shape[0] == 1,
            "data",
            "one recorded series (T, m) or (1, T, m): task=pmmh samples the posterior given one series",
            f"{obs.shape[0]} series" if obs is not None else None,
        )
        n = 1
    plan = plan_run(
        model,
        filters,
        trials=n,
        steps=steps,
        seed=cfg.seed,
        inits_per_track=cfg.inits_per_track,
        chunk_size=cfg.chunk_size,
        memory_budget_gb=cfg.memory_budget_gb,
        device=env.device or cfg.device,
        dtype=env.dtype or cfg.dtype,
        rng_backend=cfg.rng_backend,
        observations=obs,
        states=None if data is None else data.states,
        prior=None if data is None else data.prior,
    )
    return plan, sha


def _settings(cfg: DictConfig, plan, sha) -> dict:
    s = plan.settings
    return {
        "trials": s.trials,
        "steps": s.steps,
        "seed": s.seed,
        "device": str(s.device),
        "dtype": str(s.dtype).replace("torch.", ""),
        "rng_backend": s.rng_backend,
        "threads": torch.get_num_threads(),
        "data": cfg.get("data"),
        "data_sha256": sha,
    }


def _mean_se(values: torch.Tensor) -> tuple:
    """``(mean, standard error over the entries)`` of a 1-D tensor (se ``None`` for one entry)."""
    v = values.double()
    se = float(v.std() / math.sqrt(v.numel())) if v.numel() > 1 else None
    return float(v.mean()), se


# ---- task=smooth ---------------------------------------------------------------------------------


def smoothing_methods(cfg: DictConfig, filters: Mapping, labels: Mapping) -> Dict[str, str]:
    """``{label: the smoother it runs}`` for ``smooth.method``; a filter it does not fit is a
    :class:`ConfigError` naming ``smooth.method`` and the filter's key."""
    from torchflow.smoothing import smoothing_method

    key_of = {v: k for k, v in labels.items()}
    method = cfg.smooth.method
    out = {}
    for name, f in filters.items():
        try:
            out[name] = smoothing_method(f, method)
        except ArgumentError as e:
            why = str(e).split(": ", 1)[1] if str(e).startswith("method: ") else str(e)
            raise ConfigError(
                f"smooth.method: {why} (filter.{key_of.get(name, name)}); select filters it fits or "
                f"another smooth.method"
            ) from None
    return out


def _smoothing_chunk(f, method: str, trials: int, steps: int, d: int, n_paths: int, budget_gb: float) -> int:
    """Trials smoothed per call: what the forward pass keeps for the backward one (every step's
    particles and log-weights, or the Kalman family's means and covariances, and the paths) within
    ``budget_gb`` (an estimate: 4 copies of it)."""
    item = 8
    if method == "rts":
        per_trial = 3 * (steps + 1) * (d * d + d) * item
    else:
        per_trial = (steps + 1) * (f.n_particles * (d + 2) + n_paths * d) * item
    return max(1, min(trials, int(budget_gb * 2**30 // (4 * per_trial))))


def smooth_job(cfg: DictConfig, model, filters: Dict, labels: Dict, out: Path, env) -> int:
    """``task=smooth``: simulate (or read ``data=``), filter and smooth every trial with each
    filter, write ``smoothed.csv``, ``smoothing.json`` and ``smoothed.png``; the exit status."""
    from torchflow.smoothing import smooth

    methods = smoothing_methods(cfg, filters, labels)
    n_paths = cfg.smooth.n_paths
    require(
        isinstance(n_paths, int) and not isinstance(n_paths, bool) and n_paths >= 1,
        "smooth.n_paths",
        "a positive number of paths",
        n_paths,
    )
    path_chunk = cfg.smooth.path_chunk
    require(
        path_chunk is None or (isinstance(path_chunk, int) and not isinstance(path_chunk, bool) and path_chunk >= 1),
        "smooth.path_chunk",
        "a positive number of paths or null",
        path_chunk,
    )
    plan, sha = _data(cfg, model, filters, env)
    s, traj = plan.settings, plan.traj
    truth = None if traj.states is None else traj.states
    B, T, d = s.trials, s.steps, model.state_dim
    paths_gb = (T + 1) * n_paths * d * 8 / 2**30  # one trial's smoothed paths, held whole
    if any(m != "rts" for m in methods.values()) and paths_gb > s.memory_budget_gb:
        raise ConfigError(
            f"smooth.n_paths: {n_paths} paths of {T + 1} steps x d = {d} take {paths_gb:.3g} GiB per trial, more than "
            f"memory_budget_gb = {s.memory_budget_gb:g}; choose fewer paths (or a larger memory_budget_gb)"
        )
    results, rows, interrupted = {}, [], False
    for name, f in filters.items():
        if STOP.requested:
            interrupted = True
            break
        method = methods[name]
        chunk = _smoothing_chunk(f, method, B, T, d, n_paths, s.memory_budget_gb)
        log.info(
            f"{name}: {method} smoother, {B} trials x {T} steps"
            + ("" if method == "rts" else f", {n_paths} paths")
            + (f", {chunk} trials per call" if chunk < B else "")
        )
        parts, t0 = [], time.perf_counter()
        try:
            with torch.no_grad(), STOP.interruptible():
                for a in range(0, B, chunk):
                    e = min(B, a + chunk)
                    g = TrialStreams(s.seed, range(a, e), key=f.stream_name, backend=s.rng_backend)
                    parts.append(
                        smooth(
                            f,
                            traj.observations[a:e],
                            plan.mean0[a:e],
                            plan.cov0[a:e],
                            g,
                            method=method,
                            n_paths=n_paths,
                            path_chunk=path_chunk,
                        )
                    )
        except KeyboardInterrupt:
            interrupted = True
            break
        seconds = time.perf_counter() - t0
        results[name] = _smoothed(parts, plan, method, seconds)
    if not results:
        log.warning(f"interrupted by {STOP.name} before the first filter finished: nothing is written")
        return STOP.exit_code
    summary = [
        _smoothing_summary(name, r, truth, f_n=filters[name].n_particles, n_paths=n_paths)
        for name, r in results.items()
    ]
    log.info(
        f"\n{type(model).__name__}: {B} trials x {T} steps"
        + (f" of data={cfg.data}" if cfg.get("data") else "")
        + f", seed {s.seed}, {s.device}/{str(s.dtype).replace('torch.', '')}"
    )
    log.info(format_table(summary, SMOOTH_COLUMNS))
    for name, r in results.items():
        rows += smoothed_rows(name, r, truth)
    writer = shell.Output(out)
    writer.attempt("smoothed.csv", writers.write_csv, out / "smoothed.csv", rows, smoothed_columns(d))
    writer.attempt(
        "smoothing.json",
        writers.write_text,
        out / "smoothing.json",
        json.dumps(
            {
                "config": OmegaConf.to_container(cfg, resolve=True),
                "run": _settings(cfg, plan, sha),
                "summary": summary,
                "interrupted": interrupted,
                "not_run": [n for n in filters if n not in results],
            },
            indent=1,
        ),
    )
    if cfg.plots:
        title = f"{type(model).__name__}: trial 0" + (" of recorded data" if truth is None else "")
        writer.attempt(
            "smoothed.png",
            figures.save_smoothing_figure,
            out / "smoothed.png",
            None if truth is None else truth[0].cpu(),
            {n: _trial0(r) for n, r in results.items()},
            title,
        )
    if writer.failed is None:
        log.info(f"results: {shell.shown_path(out)}")
    if interrupted:
        log.warning(
            f"interrupted by {STOP.name}: the results of the filters that finished are written; not run: "
            f"{', '.join(n for n in filters if n not in results)}"
        )
        return STOP.exit_code
    return 1 if writer.failed else 0


#: the columns of the smoothing summary (terminal table and ``smoothing.json``)
SMOOTH_COLUMNS = [
    "filter",
    "method",
    "n_particles",
    "n_paths",
    "trials",
    "steps",
    "rmse_filtered",
    "rmse_filtered_se",
    "rmse_smoothed",
    "rmse_smoothed_se",
    "rmse_change",
    "rmse_change_se",
    "log_evidence",
    "seconds",
]


def _smoothed(parts, plan, method: str, seconds: float) -> dict:
    """One filter's smoothing results on the CPU: ``(B, T+1, d)`` filtered and smoothed means and
    standard deviations (filtered at step 0: the prior), the ``(B,)`` log-evidence."""
    mean = torch.cat([p.means for p in parts]).cpu()
    if method == "rts":
        sd = torch.cat([p.covariances for p in parts]).diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt().cpu()
    else:  # the spread of the M smoothing paths
        sd = torch.cat([p.paths.std(1, unbiased=False) for p in parts]).cpu()
    f_mean = torch.cat([p.filtered.estimates for p in parts]).cpu()
    f_sd = torch.cat([p.filtered.std for p in parts]).cpu()
    prior_sd = plan.cov0.diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt().cpu()
    return {
        "method": method,
        "mean": mean,
        "sd": sd,
        "seconds": seconds,
        "filtered_mean": torch.cat([plan.mean0.cpu().unsqueeze(1), f_mean], 1),
        "filtered_sd": torch.cat([prior_sd.unsqueeze(1), f_sd], 1),
        "log_evidence": torch.cat([p.filtered.log_evidence for p in parts]).cpu(),
    }


def _trial0(r: dict) -> dict:
    return {k: r[k][0] for k in ("mean", "sd", "filtered_mean", "filtered_sd")}


def _smoothing_summary(name: str, r: dict, truth: Optional[torch.Tensor], f_n, n_paths: int) -> dict:
    B, T1 = r["mean"].shape[:2]
    row = {
        "filter": name,
        "method": r["method"],
        "n_particles": f_n,
        "n_paths": None if r["method"] == "rts" else n_paths,
        "trials": B,
        "steps": T1 - 1,
        "log_evidence": float(r["log_evidence"].double().mean()),
        "seconds": r["seconds"],
    }
    if truth is not None:  # per trial: the RMSE averaged over steps 1..T; mean and se over trials
        x = truth[:, 1:].cpu()
        err_f = metrics.rmse(r["filtered_mean"][:, 1:].to(x.dtype), x).mean(1)
        err_s = metrics.rmse(r["mean"][:, 1:].to(x.dtype), x).mean(1)
        row["rmse_filtered"], row["rmse_filtered_se"] = _mean_se(err_f)
        row["rmse_smoothed"], row["rmse_smoothed_se"] = _mean_se(err_s)
        row["rmse_change"], row["rmse_change_se"] = _mean_se(err_s - err_f)
    return row


def smoothed_columns(d: int) -> List[str]:
    """``smoothed.csv``'s columns: ``filter, method, trial, step``, then per coordinate j the truth,
    the filtered and the smoothed mean and sd (``truth_j, filtered_mean_j, filtered_sd_j,
    smoothed_mean_j, smoothed_sd_j``)."""
    per = ("truth", "filtered_mean", "filtered_sd", "smoothed_mean", "smoothed_sd")
    return ["filter", "method", "trial", "step", *(f"{k}_{j}" for k in per for j in range(d))]


def smoothed_rows(name: str, r: dict, truth: Optional[torch.Tensor]) -> List[dict]:
    """The rows of ``smoothed.csv`` of one filter (:func:`smoothed_columns`); step 0 is the initial
    state (its filtered columns: the filters' prior)."""
    B, T1, d = r["mean"].shape
    cols = {
        "filtered_mean": r["filtered_mean"],
        "filtered_sd": r["filtered_sd"],
        "smoothed_mean": r["mean"],
        "smoothed_sd": r["sd"],
    }
    if truth is not None:
        cols["truth"] = truth.cpu()
    flat = {k: v.double().reshape(B * T1, d).tolist() for k, v in cols.items()}
    rows = []
    for i in range(B * T1):
        row = {"filter": name, "method": r["method"], "trial": i // T1, "step": i % T1}
        for k, v in flat.items():
            row.update({f"{k}_{j}": v[i][j] for j in range(d)})
        rows.append(row)
    return rows


# ---- task=pmmh -----------------------------------------------------------------------------------


def prior_from_config(name: str, spec, dtype=torch.float64):
    """A ``torch.distributions`` prior from its config ``{dist: <class name>, <argument>: <value>, ...}``
    (``{dist: Uniform, low: -1, high: 1}``; a list value is a vector argument); any problem is a
    :class:`ConfigError` naming ``pmmh.priors.<name>``."""
    import torch.distributions as D

    key = f"pmmh.priors.{name}"
    spec = OmegaConf.to_container(spec, resolve=True) if OmegaConf.is_config(spec) else spec
    require(
        isinstance(spec, dict) and isinstance(spec.get("dist"), str),
        key,
        "{dist: <a torch.distributions class>, <its arguments>}, e.g. {dist: Uniform, low: -1, high: 1}",
        spec,
    )
    args = {k: v for k, v in spec.items() if k != "dist"}
    cls = getattr(D, spec["dist"], None)
    if not (isinstance(cls, type) and issubclass(cls, D.Distribution)) or cls is D.Distribution:
        close = rc.close_keys(
            spec["dist"],
            [n for n in dir(D) if isinstance(getattr(D, n), type) and issubclass(getattr(D, n), D.Distribution)],
        )
        hint = f"; did you mean {' or '.join(close)}?" if close else ""
        raise ConfigError(
            f"{key}.dist: expected a torch.distributions class (Normal, Uniform, Gamma, Beta, "
            f"LogNormal, HalfNormal, ...), got {spec['dist']!r}{hint}"
        )
    try:
        tensors = {k: v if isinstance(v, bool) else torch.as_tensor(v, dtype=dtype) for k, v in args.items()}
        return cls(**tensors, validate_args=True)
    except (TypeError, ValueError, RuntimeError) as e:
        given = ", ".join(f"{k}={v}" for k, v in args.items())
        hint = (
            f"; an override is merged into the prior the experiment already sets, so to replace it delete that "
            f"one first: '~{key}' '+{key}={{dist: {spec['dist']}, ...}}'"
            if "unexpected keyword" in str(e)
            else ""
        )
        raise ConfigError(f"{key}: {spec['dist']}({given}) is refused by torch.distributions: {e}{hint}") from None


def priors_from_config(cfg: DictConfig, model) -> dict:
    """``{parameter: prior}`` from ``pmmh.priors``, each a per-trial parameter of ``model``,
    one :func:`~torchflow.inference.per_trial_values` accepts; a :class:`ConfigError` naming the key
    otherwise."""
    from torchflow.inference import per_trial_values

    given = cfg.pmmh.get("priors") or {}
    declared = list(getattr(model, "per_trial_parameters", ()) or ())
    kind = type(model).__name__
    if not declared:
        raise ConfigError(
            f"model: task=pmmh samples parameters that a model declares per trial (one value per chain); "
            f"{kind} declares none (StochasticVolatility does: mu, rho, sigma)"
        )
    require(
        len(given) > 0,
        "pmmh.priors",
        f"a prior for at least one of {kind}'s per-trial parameters "
        f"({', '.join(declared)}), e.g. '+pmmh.priors={{{declared[0]}: {{dist: Normal, loc: 0, scale: 1}}}}'",
        "none",
    )
    priors = {}
    for name, spec in given.items():
        if name not in declared:
            close = rc.close_keys(str(name), declared)
            hint = f"; did you mean {' or '.join(close)}?" if close else ""
            raise ConfigError(
                f"pmmh.priors.{name}: expected a per-trial parameter of {kind} ({', '.join(declared)}), "
                f"got {name!r}{hint}"
            )
        priors[name] = prior_from_config(name, spec)
        shape = tuple(getattr(model, name).shape)
        got = tuple(priors[name].batch_shape + priors[name].event_shape)
        require(
            got == shape, f"pmmh.priors.{name}", f"a prior of {name}'s shape {shape or '(scalar)'}", got or "(scalar)"
        )
        try:  # what the chains will do: one value per chain (here the model's own, one chain)
            with per_trial_values(model, {name: getattr(model, name).detach().unsqueeze(0)}):
                pass
        except ArgumentError as e:
            raise ConfigError(f"pmmh.priors.{name}: {e}") from None
        domain = parameter_domain(model, name)
        if not support_within(priors[name].support, domain):
            raise ConfigError(
                f"pmmh.priors.{name}: {type(priors[name]).__name__}'s support ({priors[name].support}) reaches "
                f"outside {name}'s domain ({domain}) in {type(model).__name__}: its draws would not be valid "
                "values; choose a prior on that domain "
                "(a positive parameter: Gamma, LogNormal or HalfNormal)"
            )
    return priors


def check_pmmh_filter(key: str, f) -> None:
    """A likelihood estimator for PMMH: a weighted particle filter (its log-evidence estimate is
    unbiased in exp) or the Kalman filter (exact on a linear-Gaussian model); else a
    :class:`ConfigError` naming ``filter.<key>``."""
    from torchflow.filters import KalmanFilter
    from torchflow.filters.base import ParticleFilter

    if isinstance(f, KalmanFilter) or (isinstance(f, ParticleFilter) and f.estimates_evidence):
        return
    raise ConfigError(
        f"filter.{key}: task=pmmh needs a filter whose log-evidence estimates the likelihood without "
        f"bias (a weighted particle filter: bpf, pfpf_ledh, pfpf_edh, upf, gpfis, ...; or kf on a "
        f"linear-Gaussian model, exact), got {type(f).__name__}, whose log-evidence is an approximation"
    )


def _int(cfg, key: str, minimum: int) -> int:
    v = OmegaConf.select(cfg, key)
    require(isinstance(v, int) and not isinstance(v, bool) and v >= minimum, key, f"an integer >= {minimum}", v)
    return v


def _init(cfg: DictConfig, priors: dict) -> Optional[dict]:
    init = cfg.pmmh.get("init")
    if init is None:
        return None
    init = OmegaConf.to_container(init, resolve=True) if OmegaConf.is_config(init) else init
    require(isinstance(init, dict), "pmmh.init", "null or {parameter: starting value}", init)
    for name in init:
        require(name in priors, f"pmmh.init.{name}", f"a parameter with a prior ({', '.join(priors)})", name)
    missing = [n for n in priors if n not in init]
    require(
        not missing, "pmmh.init", f"a starting value for every parameter with a prior (missing {missing})", sorted(init)
    )
    out = {}
    for name, v in init.items():
        t = torch.as_tensor(v, dtype=torch.float64)
        if not bool(priors[name].support.check(t).all()):
            raise ConfigError(
                f"pmmh.init.{name}: expected a value inside the support of its prior "
                f"({priors[name].support}), got {v!r}"
            )
        out[name] = t
    return out


def _initial_prior(model, plan):
    """The filters' prior of the initial state for PMMH: ``params -> (mean, cov)`` from the model's
    declared prior at the chains' values (it depends on them: a stationary law), or the prior of the
    run's trial 0 where the model declares none."""
    from torchflow.app.data import declared_prior
    from torchflow.inference import per_trial_values
    from torchflow.models.base import StateSpaceModel

    if getattr(type(model), "declared_prior", None) in (None, StateSpaceModel.declared_prior):
        return plan.mean0[0], plan.cov0[0]

    def prior(params):
        C = next(iter(params.values())).shape[0]
        with per_trial_values(model, params):
            return declared_prior(model, C)

    return prior


def pmmh_job(cfg: DictConfig, model, filters: Dict, labels: Dict, out: Path, env) -> int:
    """``task=pmmh``: the series (trial 0 of a simulation, or ``data=``), PMMH with each filter,
    then ``posterior.csv``, ``pmmh.json``, ``posterior.png`` and ``traces.png``; the exit status."""
    from torchflow.inference import pmmh

    priors = priors_from_config(cfg, model)
    for key, label in labels.items():
        check_pmmh_filter(key, filters[label])
    chains, iterations = _int(cfg, "pmmh.chains", 1), _int(cfg, "pmmh.iterations", 4)
    adapt = _int(cfg, "pmmh.adapt", 0)
    scale, target = cfg.pmmh.scale, cfg.pmmh.target_acceptance
    require(
        isinstance(scale, (int, float)) and not isinstance(scale, bool) and scale > 0,
        "pmmh.scale",
        "a positive random-walk sd",
        scale,
    )
    require(
        target is None or (isinstance(target, (int, float)) and 0 < target < 1),
        "pmmh.target_acceptance",
        "null or a rate in (0, 1)",
        target,
    )
    init = _init(cfg, priors)
    truth = {n: getattr(model, n).detach().double().cpu().clone() for n in priors}
    plan, sha = _data(cfg, model, filters, env, one_series=True)
    series = plan.traj.observations[0]
    recorded = plan.traj.states is None
    prior = _initial_prior(model, plan)
    results, interrupted = {}, None
    for name, f in filters.items():
        log.info(
            f"{name}: PMMH of {', '.join(priors)}, {chains} chains x ({adapt} adaptation + {iterations}) "
            f"iterations on {series.shape[0]} steps" + (f" of data={cfg.data}" if recorded else " (trial 0)")
        )
        try:
            with STOP.interruptible():
                results[name] = pmmh(
                    f,
                    series,
                    prior,
                    priors,
                    cfg.seed,
                    n_chains=chains,
                    n_iterations=iterations,
                    n_adapt=adapt,
                    init=init,
                    scale=float(scale),
                    target_acceptance=None if target is None else float(target),
                )
        except KeyboardInterrupt:
            interrupted = name
            break
    if interrupted is not None and not results:
        log.warning(f"interrupted by {STOP.name} during PMMH: a chain cut short is no sample; nothing is written")
        return STOP.exit_code
    if interrupted is not None:  # what finished is kept, as the run command keeps finished filters
        log.warning(
            f"interrupted by {STOP.name} during {interrupted}'s PMMH: its chains cut short are no sample and are "
            f"not written; the finished posteriors ({', '.join(results)}) are"
        )
    known = None if recorded else truth
    summary = {name: pmmh_summary(r, known) for name, r in results.items()}
    table = [{"filter": name, "parameter": p, **v} for name, s in summary.items() for p, v in s["parameters"].items()]
    log.info(f"\n{type(model).__name__}: PMMH on {series.shape[0]} steps, seed {cfg.seed}")
    log.info(format_table(table, PMMH_COLUMNS))
    for name, s in summary.items():
        log.info(f"{name}: acceptance per chain {', '.join(f'{a:.2f}' for a in s['acceptance'])}; {s['seconds']:.1f} s")
    for name, s in summary.items():
        for line in convergence_warnings(name, s):
            log.warning(line)
    writer = shell.Output(out)
    rows = [row for name, r in results.items() for row in posterior_rows(name, r)]
    writer.attempt("posterior.csv", writers.write_csv, out / "posterior.csv", rows, posterior_columns(results))
    writer.attempt(
        "pmmh.json",
        writers.write_text,
        out / "pmmh.json",
        json.dumps(
            {
                "config": OmegaConf.to_container(cfg, resolve=True),
                "run": {
                    **_settings(cfg, plan, sha),
                    "trials": 1,
                    "series": "data" if recorded else "trial 0 of the simulation",
                    "chains": chains,
                    "iterations": iterations,
                    "adapt": adapt,
                    "interrupted": interrupted,
                    "not_run": [n for n in filters if n not in results],
                },
                "priors": {n: OmegaConf.to_container(cfg.pmmh.priors[n], resolve=True) for n in priors},
                "filters": summary,
            },
            indent=1,
        ),
    )
    if cfg.plots:
        draws = {name: {n: v.detach().double().cpu() for n, v in r.samples.items()} for name, r in results.items()}
        title = f"{type(model).__name__}: PMMH, {chains} chains x {iterations} draws"
        writer.attempt("posterior.png", figures.save_posterior_figures, out, draws, known, title)
    if writer.failed is None:
        log.info(f"results: {shell.shown_path(out)}")
    if interrupted is not None:
        return STOP.exit_code
    return 1 if writer.failed else 0


#: the chains are called unconverged above this split R-hat or below this effective sample size
#: (the thresholds of Vehtari et al. 2021: R-hat < 1.01 for publication, 1.05 as a first screen; ESS >= 100)
RHAT_MAX, ESS_MIN = 1.05, 100


def convergence_warnings(name: str, s: dict) -> List[str]:
    """One line per parameter of filter ``name``'s PMMH summary ``s`` (:func:`pmmh_summary`) whose
    split R-hat exceeds :data:`RHAT_MAX` or whose ESS is below :data:`ESS_MIN`: its summaries are
    not yet a posterior (more iterations, chains, or a better-tuned proposal)."""
    lines = []
    for p, v in s["parameters"].items():
        why = []
        if v["rhat"] is not None and not v["rhat"] <= RHAT_MAX:  # NaN counts as not converged
            why.append(f"R-hat {v['rhat']:.3g} > {RHAT_MAX}")
        if v["ess"] is not None and not v["ess"] >= ESS_MIN:
            why.append(f"ESS {v['ess']:.3g} < {ESS_MIN}")
        if why:
            lines.append(
                f"{name}: {p}: the chains have not converged ({', '.join(why)}): its mean and sd are not yet "
                f"the posterior's; run more iterations (pmmh.iterations) or chains (pmmh.chains)"
            )
    return lines


#: the columns of the PMMH table (terminal) and of each parameter's entry in ``pmmh.json``
PMMH_COLUMNS = ["filter", "parameter", "truth", "mean", "sd", "mcse", "rhat", "ess", "ess_per_sec"]


def pmmh_summary(r, truth: Optional[Dict[str, torch.Tensor]]) -> dict:
    """One filter's PMMH in numbers: per scalar parameter component the truth (``None``: unknown),
    posterior mean and sd over all chains, Monte Carlo standard error ``sd / sqrt(ESS)``, split
    R-hat, ESS and ESS per second; the acceptance rate and scale per chain; the seconds."""
    params = {}
    for name, v in r.samples.items():
        comps = figures.scalar_series({name: v.detach().double().cpu()})
        rh = r.rhat.get(name)
        es = r.ess.get(name)
        t = None if truth is None else truth[name].reshape(-1)
        for i, (cname, draws) in enumerate(comps.items()):
            ess = None if es is None else float(es.reshape(-1)[i])
            sd = float(draws.std())
            params[cname] = {
                "truth": None if t is None else float(t[i]),
                "mean": float(draws.mean()),
                "sd": sd,
                "mcse": None if not ess else sd / math.sqrt(ess),
                "rhat": None if rh is None else float(rh.reshape(-1)[i]),
                "ess": ess,
                "ess_per_sec": None if ess is None else ess / r.seconds,
            }
    out = {
        "parameters": params,
        "acceptance": r.acceptance.tolist(),
        "scale": r.scale.tolist(),
        "seconds": r.seconds,
        "mean_log_likelihood": float(r.log_likelihood.double().mean()),
    }
    out["converged"] = not convergence_warnings("", out)
    return out


def posterior_columns(results: Mapping) -> List[str]:
    """``posterior.csv``'s columns: ``filter, chain, iteration, log_likelihood``, then one per scalar
    parameter component (``rho``; a vector ``beta``: ``beta_0, beta_1, ...``)."""
    names = []
    for r in results.values():
        for name, v in r.samples.items():
            names += [c for c in figures.scalar_series({name: v}) if c not in names]
    return ["filter", "chain", "iteration", "log_likelihood", *names]


def posterior_rows(name: str, r) -> List[dict]:
    """The rows of ``posterior.csv`` of one filter: chain c (0-based), kept iteration 1..S."""
    comps = {}
    for pname, v in r.samples.items():
        comps.update({k: c.tolist() for k, c in figures.scalar_series({pname: v.detach().double().cpu()}).items()})
    ll = r.log_likelihood.double().cpu().tolist()
    C, S = r.log_likelihood.shape
    return [
        {
            "filter": name,
            "chain": c,
            "iteration": s + 1,
            "log_likelihood": ll[c][s],
            **{k: v[c][s] for k, v in comps.items()},
        }
        for c in range(C)
        for s in range(S)
    ]


def task_job(task: str, cfg: DictConfig, model, filters: Dict, labels: Dict, out: Path, env) -> int:
    """Run ``task`` (``smooth`` | ``pmmh``) of the ``torchflow`` command; the exit status."""
    try:
        return (smooth_job if task == "smooth" else pmmh_job)(cfg, model, filters, labels, out, env)
    except RunStopped as stopped:  # during the simulation: nothing computed, nothing written
        log.warning(str(stopped))
        return STOP.exit_code


__all__ = [
    "TASKS",
    "check_task",
    "smooth_job",
    "pmmh_job",
    "prior_from_config",
    "priors_from_config",
    "check_pmmh_filter",
    "smoothing_methods",
    "smoothed_columns",
    "smoothed_rows",
    "posterior_columns",
    "posterior_rows",
    "pmmh_summary",
    "convergence_warnings",
    "RHAT_MAX",
    "ESS_MIN",
    "task_job",
]
