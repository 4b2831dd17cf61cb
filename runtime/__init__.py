"""cmnav runtime: the flight program on the companion computer (never imports torch)."""
