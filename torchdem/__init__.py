"""torchdem: a batched tensor DEM, the draw down test and its model extensions. Never imports ``bo``."""
