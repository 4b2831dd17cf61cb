"""The simulated world: rooms with obstacles, camera rendering, quadrotor dynamics, collisions,
degradation models, the SITL vehicle (``sim.sitl``) and its launcher (``sim.sitl_session``).

Import the submodules themselves (``sim.world``, ``sim.render``, ...): this package imports
nothing, so a light submodule (the SITL session launcher, the plots) does not load torch.
"""
