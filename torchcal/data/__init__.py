"""Loading and validation of measurement files: CSV in, typed SI tensors out."""
