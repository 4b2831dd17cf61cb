"""An autopilot's velocity response, measured and identified (issue 27): fly one command sequence
(:mod:`.sequence`) through the runtime's own MAVSDK adapter on PX4 or on our SITL vehicle
(:mod:`.flight`), then fit delay, time constant, gain and acceleration limit per axis, the height
drift and the landing drift (:mod:`.identify`); read recorded policy flights on PX4 back, its
estimate against the ground truth and the model replayed on the commands sent (:mod:`.replay`).
``python -m sim.response --help``."""
