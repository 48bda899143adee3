"""Training: event binning, losses and metrics for fitting Gaussians to blurry frames plus events."""
