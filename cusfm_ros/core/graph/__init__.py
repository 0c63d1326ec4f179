"""View graph: which image pairs to match (pose-graph priors), pose graph optimization."""
