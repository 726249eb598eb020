"""Parameter estimation: objective, screening, SQP and baselines, observer, online adapter."""
