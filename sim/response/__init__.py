"""An autopilot's velocity response, measured and identified (issue 27): fly one command sequence
(:mod:`.sequence`) through the runtime's own MAVSDK adapter on PX4 or on our SITL vehicle
(:mod:`.flight`), then fit delay, time constant, gain and acceleration limit per axis, the height
drift and the landing drift (:mod:`.identify`).  ``python -m sim.response --help``."""
