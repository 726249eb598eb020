"""Sensor models: PT100-like readings with white noise and quantisation."""
from __future__ import annotations

import numpy as np


def pt100(true_c: np.ndarray | float, rng: np.random.Generator, sigma_k: float = 0.1, resolution_k: float = 0.1) -> np.ndarray:
    """Readings of a PT100 chain: true temperature + N(0, sigma²) noise, rounded to ``resolution``.

    Parameters
    ----------
    true_c : ndarray or float
        True temperatures, °C.
    sigma_k : float
        Noise standard deviation, K (0 disables noise).
    resolution_k : float
        Quantisation step, K (0 disables quantisation).
    """
    y = np.asarray(true_c, dtype=float) + (rng.normal(0.0, sigma_k, np.shape(true_c)) if sigma_k > 0 else 0.0)
    return np.round(y / resolution_k) * resolution_k if resolution_k > 0 else y
