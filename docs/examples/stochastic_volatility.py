"""Your own model: stochastic volatility

A model of your own is a subclass of `torchflow.models.StateSpaceModel`, the core of the model
contract: its dimensions, the true initial state and the filters' prior, a way to draw and to
score the transition, and a way to draw and to score the measurement, six methods. That is all
the bootstrap particle filter needs, and `simulate()` follows from it. Here, the
stochastic-volatility model, in the parametrisation of the `particles` library's `StochVol`

    x_t - mu = rho (x_{t-1} - mu) + sigma v_t,     v_t ~ N(0, 1)
    y_t | x_t ~ N(0, exp(x_t))

whose measurement is not a function of the state plus Gaussian noise, so this class gives no
Gaussian form (`torchflow.models.GaussianStateSpaceModel`): the Kalman-type filters and the flows,
which linearise h(x), refuse it when they are built, and the bootstrap particle filter runs it
(the built-in `torchflow.models.StochasticVolatility`, `model=stochastic_volatility`, is the same
core with two Gaussian forms added, for the flows and the Kalman family). The
model holds its parameters as buffers, so `model.double()`, `model.to("cuda")` and learning
(`nn.Parameter`s instead of buffers) work as for the built-in models. Its random draws go through
`torchflow.core.linalg.standard_normal`, which takes a `torch.Generator` or torchflow's per-trial
random streams (`torchflow.core.random.TrialStreams`, what the command-line runner passes).

The script simulates a few trials with the model's own `simulate()`, runs
`torchflow.filters.BootstrapParticleFilter` on them, shows the refusal of a filter that needs the
Gaussian form, and draws the first trial's log-volatility, its filtered estimate and the
observations. [Define your own model](../guide/custom-models.md) has the whole contract.
"""

import math

import matplotlib.pyplot as plt
import torch

from torchflow.core.linalg import standard_normal
from torchflow.core.random import TrialStreams
from torchflow.filters import BootstrapParticleFilter, ExtendedKalmanFilter
from torchflow.models import StateSpaceModel

LOG_2PI = math.log(2 * math.pi)


def normal_like(x, generator):
    """N(0, 1) draws shaped like x, from a torch.Generator or torchflow's per-trial streams."""
    return standard_normal(x.shape, dtype=x.dtype, device=x.device, generator=generator)


class StochasticVolatility(StateSpaceModel):
    state_dim = 1
    obs_dim = 1

    def __init__(self, mu=-1.02, rho=0.9702, sigma=0.178):  # particles' StochVol defaults
        super().__init__()
        self.register_buffer("mu", torch.tensor(mu, dtype=torch.float64))
        self.register_buffer("rho", torch.tensor(rho, dtype=torch.float64))
        self.register_buffer("sigma", torch.tensor(sigma, dtype=torch.float64))

    # the true x_0 of each of B trials, (B, 1): a draw from the stationary law N(mu, sigma^2 / (1 - rho^2))
    def initial_state(self, batch_size, generator=None):
        x0 = torch.zeros(batch_size, 1, dtype=self.dtype, device=self.device)
        stationary_sd = self.sigma / torch.sqrt(1 - self.rho**2)
        return self.mu + stationary_sd * normal_like(x0, generator)

    # the filters' prior N(mean (B, 1), cov (B, 1, 1)): the stationary law, whatever the truth
    def initial_belief(self, states0, generator=None):
        B = states0.shape[0]
        stationary_var = self.sigma**2 / (1 - self.rho**2)
        return self.mu * states0.new_ones(B, 1), stationary_var * states0.new_ones(B, 1, 1)

    # x ~ p(x_t | x_{t-1} = x), for x of any shape (..., 1)
    def sample_transition(self, x, generator=None):
        return self.mu + self.rho * (x - self.mu) + self.sigma * normal_like(x, generator)

    # log p(x_next | x) -> (...)
    def transition_log_prob(self, x_next, x):
        r = (x_next - self.mu - self.rho * (x - self.mu)) / self.sigma
        return (-0.5 * r**2 - torch.log(self.sigma) - 0.5 * LOG_2PI).sum(-1)

    # y ~ p(y_t | x_t = x) = N(0, exp(x))
    def sample_measurement(self, x, generator=None):
        return torch.exp(x / 2) * normal_like(x, generator)

    # log p(y | x) -> (...), y broadcast against x's leading shape
    def measurement_log_prob(self, z, x):
        return (-0.5 * z**2 * torch.exp(-x) - 0.5 * x - 0.5 * LOG_2PI).sum(-1)


model = StochasticVolatility()
g = torch.Generator().manual_seed(0)

# simulate B trials of T steps: simulate() follows from initial_state, sample_transition and sample_measurement
B, T = 8, 200
data = model.simulate(B, T, g)
states, observations = data.states, data.observations  # (B, T+1, 1), (B, T, 1)

mean, cov = model.initial_belief(states[:, 0])
bpf = BootstrapParticleFilter(model, n_particles=1000)
res = bpf(observations, mean, cov, torch.Generator().manual_seed(1))

rmse = ((res.estimates - states[:, 1:]) ** 2).mean().sqrt()
prior_rmse = ((states[:, 1:] - model.mu) ** 2).mean().sqrt()  # the stationary mean mu as the estimate
print(f"RMSE of the filtered log-volatility {rmse:.3f} (the stationary mean: {prior_rmse:.3f})")
print(f"log-evidence per trial: {res.log_evidence.mean():.1f} (mean of {B} trials)")
print(f"mean ESS: {res.ess.mean():.0f} of {bpf.n_particles} particles")

# the same filter with one random stream per trial: trial b's numbers no longer depend on the batch
per_trial = bpf(observations, mean, cov, TrialStreams(seed=1, trials=B, key="bpf"))
rmse_streams = ((per_trial.estimates - states[:, 1:]) ** 2).mean().sqrt()
print(f"with per-trial random streams: RMSE {rmse_streams:.3f}")

# a filter that needs the Gaussian form (transition_mean, transition_cov, measure, measurement_cov) refuses the model
try:
    ExtendedKalmanFilter(model)
except TypeError as err:
    print(err)

t = torch.arange(1, T + 1)
fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(10, 5), sharex=True)
ax1.plot(t, observations[0, :, 0], ".", ms=3, color="0.4")
ax1.set(ylabel="y_t", title="observations (trial 0)")
ax2.plot(t, states[0, 1:, 0], "k-", lw=1.5, label="true x_t")
ax2.plot(t, res.estimates[0, :, 0], "C1-", lw=1.2, label="bootstrap PF estimate")
ax2.set(xlabel="t", ylabel="log-volatility x_t")
ax2.legend(fontsize=8)
fig.tight_layout()

if __name__ == "__main__":  # run by hand: show the figure (the documentation build saves it instead)
    plt.show()
