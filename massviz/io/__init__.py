"""Reading and writing: recordings and their formats, weights, the trace cache, challenge CSVs, atomic writes."""
