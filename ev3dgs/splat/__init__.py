"""Gaussian splatting core: projection, rasterizers (reference oracle, CPU tiles, CUDA), SH, model, strategy."""
