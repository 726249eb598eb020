"""Benchmarks behind ``thermal-edge bench …``: tables side by side with their baselines."""
