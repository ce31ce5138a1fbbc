"""From events and a model to J and dJ/dtheta: the problem, the fused driver, the generic kernel chain,
the multi-cluster problem."""
