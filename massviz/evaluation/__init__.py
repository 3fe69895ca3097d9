"""Evaluation: the CORSMAL score, sweeps, baselines, failure analysis and tuning state, all over traces."""
