"""pgm: batched exact and particle belief propagation in PyTorch.

Generic: knows nothing of bodies, cameras or images. One engine for discrete states and
(next) particles: a node's support is K points with a log-measure, a pairwise factor is a
log-potential over two supports (or a structured message kernel), and the semiring decides
whether inference computes marginals, MAP or counts.
"""

from pgm.chain import InfeasibleError, chain_inference, chain_map
from pgm.factors import BandedMonotoneFactor, MonotoneFactor, PairwiseFactor, TableFactor
from pgm.graph import FactorGraph, GraphError, NotATreeError
from pgm.loopy import loopy_bp
from pgm.semiring import (
    CountingSemiring,
    LogSemiring,
    MaxSemiring,
    Semiring,
    TemperedSemiring,
)
from pgm.tree import InferenceResult, tree_inference, tree_map

__all__ = [
    "BandedMonotoneFactor",
    "CountingSemiring",
    "FactorGraph",
    "GraphError",
    "InfeasibleError",
    "InferenceResult",
    "LogSemiring",
    "MaxSemiring",
    "MonotoneFactor",
    "NotATreeError",
    "PairwiseFactor",
    "Semiring",
    "TableFactor",
    "TemperedSemiring",
    "chain_inference",
    "chain_map",
    "loopy_bp",
    "tree_inference",
    "tree_map",
]
