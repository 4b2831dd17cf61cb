"""cmnav: the `cmnav` console command (a thin dispatcher over the project's packages)."""
