"""Training SAEs on captured residual rows with SAELens."""
