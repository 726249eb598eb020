"""thermal_edge: online-adapted LPTN thermal protection for PM machines."""

__version__ = "0.1.0"
