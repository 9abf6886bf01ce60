"""Write the GBP/USD returns series that ``particles`` ships as a CSV for ``torchflow data=...``.

The series is ``particles.datasets.GBP_vs_USD_9798``: 750 daily percentage log-returns,
``100 * diff(log(rate))``, 1997-01-02 to 1999-12-31. Its source file credits the PACIFIC Exchange
Rate Service (Prof. Werner Antweiler, University of British Columbia). torchflow does not ship the
numbers; this script writes them from an installed ``particles`` (``pip install particles``)::

    python -m experiments.data.gbpusd gbpusd_returns.csv
    torchflow model=stochastic_volatility data=gbpusd_returns.csv 'filter=[bpf,pfpf_ledh]'
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np


def returns() -> np.ndarray:
    """The 750 returns, from ``particles``' dataset (a clear exit when it is not installed)."""
    try:
        import particles.datasets
    except ImportError:
        raise SystemExit("experiments.data.gbpusd: needs the particles library (pip install particles)") from None
    return np.asarray(particles.datasets.GBP_vs_USD_9798().data, dtype=np.float64)


def write(path) -> Path:
    """Write the series to ``path`` as a one-column CSV with the header ``returns``."""
    path = Path(path)
    np.savetxt(path, returns(), delimiter=",", header="returns", comments="", fmt="%.17g")
    return path


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python -m experiments.data.gbpusd OUT.csv")
    print(write(sys.argv[1]))
