"""The body factor graph: parts as SE(3) nodes, their connections, and observation factors.

:mod:`motion.body.observation` -- occlusion-aware observation factors (the proposal's Eqs.
28-29) whose cues score what one shared renderer produced.
"""
