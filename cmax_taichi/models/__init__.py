"""Motion models, objectives and regularizers: one registry each, capabilities declared on the entries."""
