"""The body factor graph: parts as SE(3) nodes, their connections, and observation factors.

:mod:`motion.body.spec` -- parts, tree, frames and offsets from a skeleton, a parts file and
a motion; :mod:`motion.body.limits` -- joint-angle limits per kinematic edge;
:mod:`motion.body.graph` -- the factor graph over frames; :mod:`motion.body.observation` --
occlusion-aware observation factors (the proposal's Eqs. 28-29) whose cues score what one
shared renderer produced; :mod:`motion.body.solve` -- the posture solver on such a graph
(start particles, particle BP, the choice among searches, the polish).
"""
