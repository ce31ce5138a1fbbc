"""Independent implementations used to check the library: the float64 NumPy oracle and the PyTorch twin."""
