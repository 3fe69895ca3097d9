"""The bundled synthetic recordings (``data_samples/``): a deterministic generator (``massviz.samples.generator``)."""
