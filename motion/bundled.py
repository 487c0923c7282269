"""The motion-capture files shipped inside the package (``motion/data``; sources and terms in
its README), for examples, benchmarks and experiments that need a body without
``../shared``."""

from __future__ import annotations

from pathlib import Path

__all__ = ["DATA", "WALK_02_01", "WALK_07_01"]

#: the package's data folder
DATA = Path(__file__).resolve().parent / "data"
#: CMU trial 02_01, subject 2 walking: 344 frames at 120 Hz, 31 joints (cgspeed BVH)
WALK_02_01 = DATA / "cmu_02_01_walk.bvh"
#: CMU trial 07_01, subject 7 walking (another performer of the same action): 317 frames
WALK_07_01 = DATA / "cmu_07_01_walk.bvh"
