"""Fault injection for tests: the catalogue of faults (``catalogue``: kinds, sites, the
``KIND@SECONDS`` syntax), shared with the SITL vehicle, and the runtime's side of injecting them
(``injection``: a policy that overruns or outputs NaN, a geofence that shrinks)."""
