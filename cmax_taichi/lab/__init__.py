"""Research harnesses, not the library: the paper's experiments, the real-data tables, the segmentation
evaluation and the benchmark. The lab imports the library; the library never imports the lab."""
