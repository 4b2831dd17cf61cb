"""Benchmarks behind `cmnav bench`: each module measures one job in one run and reports ratios
measured in that run (`bench.sim`: the renderer).  Tests never assert timings; these do not
assert either, they print."""
