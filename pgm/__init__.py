"""pgm: batched exact and particle belief propagation in PyTorch.

Generic: knows nothing of bodies, cameras or images. One engine for discrete states and
particles: a node's support is K points with a log-measure, a pairwise factor is a
log-potential over two supports (or a structured message kernel), and the semiring decides
whether inference computes marginals, MAP or counts.
"""

from pgm.chain import InfeasibleError, chain_inference, chain_map
from pgm.continuous import (
    ContinuousPairwise,
    GaussianUnary,
    LinearGaussian,
    LookupGaussian,
    LookupPose,
    RigidConnection,
    UnaryFactor,
)
from pgm.factors import (
    AnnealingStep,
    BandedMonotoneFactor,
    BandedTempoFactor,
    Capability,
    FactorWrapper,
    MissingCapabilityError,
    MonotoneFactor,
    PairwiseFactor,
    TableFactor,
)
from pgm.graph import FactorGraph, GraphError, NotATreeError
from pgm.limits import EulerBox, LimitedConnection
from pgm.loopy import loopy_bp
from pgm.particle_bp import IterationStats, ParticleGraph, ParticleResult, particle_bp
from pgm.schedules import Constant, Geometric, Linear, Schedule, Stepwise
from pgm.semiring import (
    CountingSemiring,
    LogSemiring,
    MaxSemiring,
    Semiring,
    TemperedSemiring,
)
from pgm.spaces import SE3, Discrete, Euclidean, StateSpace
from pgm.templates import SpatioTemporalTemplate, TiledFactor
from pgm.tree import InferenceResult, tree_inference, tree_map

__all__ = [
    "SE3",
    "AnnealingStep",
    "BandedMonotoneFactor",
    "BandedTempoFactor",
    "Capability",
    "Constant",
    "ContinuousPairwise",
    "CountingSemiring",
    "Discrete",
    "Euclidean",
    "EulerBox",
    "FactorGraph",
    "FactorWrapper",
    "GaussianUnary",
    "Geometric",
    "GraphError",
    "InfeasibleError",
    "InferenceResult",
    "IterationStats",
    "LimitedConnection",
    "Linear",
    "LinearGaussian",
    "LogSemiring",
    "LookupGaussian",
    "LookupPose",
    "MaxSemiring",
    "MissingCapabilityError",
    "MonotoneFactor",
    "NotATreeError",
    "PairwiseFactor",
    "ParticleGraph",
    "ParticleResult",
    "RigidConnection",
    "Schedule",
    "Semiring",
    "SpatioTemporalTemplate",
    "StateSpace",
    "Stepwise",
    "TableFactor",
    "TemperedSemiring",
    "TiledFactor",
    "UnaryFactor",
    "chain_inference",
    "chain_map",
    "loopy_bp",
    "particle_bp",
    "tree_inference",
    "tree_map",
]
