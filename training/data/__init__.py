"""Gray/depth datasets: TartanAir V1/V2 loaders and the simulated-dataset generator."""
