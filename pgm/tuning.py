"""Machine-tuned constants of the inference engine, in one place.

None of these changes a result beyond floating-point rounding (and, for chunk sizes, the
order of random draws): they trade memory against per-call overhead and cache reuse. Each was
measured on the project's reference machine (2 CPU cores, torch 2.13 CPU; README,
"Particle BP") and, where it differs, on one NVIDIA H100.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = [
    "ACCELERATOR",
    "CPU",
    "EXP_FLOOR",
    "MATMUL_MIN_STATES",
    "UNSHIFTED_BOUND_MAX",
    "DeviceBudget",
    "budget_for",
]

#: Lower bound applied before ``exp()`` of log-values that are 0 at their maximum. The CPU
#: exp leaves its vectorised path below about -87.3 (float32 underflow), at a ~40x cost;
#: e^-87 = 1.6e-38, and every place that clamps recomputes exactly where the floor could
#: have decided a result.
EXP_FLOOR = -87.0

#: Below this many states a plain log-sum-exp message through a dense table is as fast as
#: the linear-space matrix product one (``TableFactor``).
MATMUL_MIN_STATES = 32

#: A table's known upper bound in ``[0, UNSHIFTED_BOUND_MAX]`` needs no shift before
#: ``exp``: entries <= e^60 keep float32 sums finite over up to 1e12 states (80 left too
#: little room), and the floor ``bound + EXP_FLOOR`` stays on exp's fast path.
UNSHIFTED_BOUND_MAX = 60.0


@dataclass(frozen=True)
class DeviceBudget:
    """How much work one batched call takes, per kind of device.

    Attributes:
        bp_table_bytes: pairwise tables ``(E, K, K)`` per BP chunk of frames. On 2 CPU
            cores ~48 MB measured best (1 to 3 chunks alike, 5 slower: per-op overhead
            against cache reuse); on a GPU chunks only bound memory.
        proposal_particles: particles per proposal chunk. The proposal is many small ops
            (its mixture densities are evaluated in blocks), so it takes large chunks.
        mixture_block_bytes: kernel-mixture density tables evaluated per block (product,
            clamp, exp, sum in cache: 2.4x faster than whole passes at K = M = 150 on 2
            CPU cores); on a GPU blocks only bound memory.
    """

    bp_table_bytes: int
    proposal_particles: int
    mixture_block_bytes: int


#: on a CPU: keep to its caches
CPU = DeviceBudget(bp_table_bytes=48 << 20, proposal_particles=1 << 20, mixture_block_bytes=4 << 20)
#: elsewhere (GPU): only bound memory
ACCELERATOR = DeviceBudget(
    bp_table_bytes=1 << 30, proposal_particles=1 << 24, mixture_block_bytes=256 << 20
)


def budget_for(device: torch.device | str) -> DeviceBudget:
    """The :class:`DeviceBudget` of a device (CPU, or any accelerator)."""
    return CPU if torch.device(device).type == "cpu" else ACCELERATOR
