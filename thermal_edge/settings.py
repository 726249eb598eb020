"""Typed settings as plain data: how a field of a settings dataclass is declared, and the online
adapter's settings.

A field declared with :func:`setting` carries its default *and* what a configuration file may
give for it (range, choices, a check); :mod:`thermal_edge.config` reads ``edge.yaml`` generically
from these declarations and ``deploy/docs`` renders the defaults from them, so every default is
stated once, here or next to its dataclass.

This module depends on nothing of the package: :mod:`thermal_edge.estimation` reads
:class:`AdapterConfig` from here, and the configuration loader needs neither the estimation
package nor scipy.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import MISSING, dataclass, field
from typing import Any

__all__ = ["METHODS", "WEIGHTINGS", "AdapterConfig", "Spec", "setting", "spec_of"]

#: optimisers of the online adapter (``adaptation.method``)
METHODS = ("sqp", "gauss_newton", "numerical")
#: weightings of the objective over the history window (``adaptation.weighting``)
WEIGHTINGS = ("paper", "forgetting", "uniform")


@dataclass(frozen=True)
class Spec:
    """What a configuration file may give for one field (the reader applies it, the docs show it).

    Attributes
    ----------
    positive : bool
        A number that must be > 0.
    min, max : float, optional
        Inclusive bounds of a number.
    choices : tuple of str, optional
        The allowed strings.
    env : str, optional
        Environment variable whose value is the default when the key is left out (a required
        field otherwise), e.g. systemd's ``STATE_DIRECTORY``.
    inline : bool
        A nested settings dataclass whose keys sit in the enclosing section itself.
    aliases : tuple of str
        Other keys of the file that give this field (e.g. ``signal`` for a one-signal ``signals``).
    check : callable, optional
        ``check(value) -> message or None`` for a rule the bounds cannot say.
    parse : callable, optional
        ``parse(section, key, values, default) -> value``: reads a field that is not a plain value
        (``values``: the fields of the same section read so far, ``default``: this field's).
    """

    positive: bool = False
    min: float | None = None
    max: float | None = None
    choices: tuple[str, ...] | None = None
    env: str | None = None
    inline: bool = False
    aliases: tuple[str, ...] = ()
    check: Callable[[Any], str | None] | None = None
    parse: Callable[..., Any] | None = None


def setting(default: Any = MISSING, *, default_factory: Any = MISSING, **spec: Any) -> Any:
    """A dataclass field with its default and its :class:`Spec` (keyword arguments)."""
    return field(default=default, default_factory=default_factory, metadata={"setting": Spec(**spec)})


def spec_of(f: Any) -> Spec:
    """The :class:`Spec` of a dataclass field (an empty one for a plain field)."""
    return f.metadata.get("setting") or Spec()


@dataclass
class AdapterConfig:
    """Settings of the online adapter (``adaptation:`` in ``edge.yaml``).

    Attributes
    ----------
    period_s : float
        Decision period ``Ts``, s (the paper: 180 s).
    threshold_k : float
        RMS prediction error over the last period above which the adapter optimises, K (about
        the sensor noise: a fit only makes a challenger, judged out of sample, so fitting often
        costs CPU, not accuracy; with 0.25 K the adapter stopped short in ``bench paper`` E2).
        The open-loop error over the last ``validate_s`` above it triggers a fit too (slow
        modes a period does not show).
    window_s : float
        History window used for estimation, s.
    min_window_s : float
        Floor on the history before optimising (s); above it the window's Fisher information
        decides (``max_rel_std``). Minutes at one operating point cannot separate capacities from
        resistances, whatever their (time-correlated) residuals suggest.
    decimate : int
        Samples per optimiser step (20 at 1 Hz: 20 s steps, short against the machine's thermal
        time constants; ZOH on the coarse grid is exact for inputs held over each step).
    max_iter : int
        SQP iteration cap per decision.
    coverage : float
        Screening keeps parameters covering this share of the optimisation potential.
    weighting : {"paper", "forgetting", "uniform"}
    tau_s : float
        Forgetting time constant for ``weighting: forgetting``, s.
    prior_weight : float
        MAP weight toward the offline values (0 = least squares), K².
    validate_s : float
        Most evidence (s, recorded after the fit) a challenger is judged on; undecided by then, it
        is dropped. It is promoted only if, besides the margin, no single sensor's RMS error over
        the evidence grows by more than ``sensor_tolerance_k`` (K) to above the parameters in
        use's RMS error over all the sensors.
    noise_k : float
        Sensor noise σ (K) assumed in the promotion margin.
    promote_z : float
        Noise margin in standard errors of the mean squared-error difference.
    min_gain : float
        Share of the champion's mean squared error above the sensor noise the challenger must
        remove over the full evidence to be promoted (more on less evidence; besides, it must be
        better consistently over the periods of the evidence: :func:`judge`).
    method : {"sqp", "gauss_newton", "numerical"}
    params : tuple of str, optional
        Adaptable parameters; default: the model's ``adaptable: true`` ones.
    sensors : tuple of str, optional
        Sensors the adapter learns from; default: all the model's sensors present.
    max_rel_std : float
        A parameter is offered to the optimiser only if the window pins it down to this relative
        standard deviation (Fisher information, all adaptable parameters free, the residuals
        counted as independent: whether the excitation and sensors separate it; the reported
        bands count their correlation in time). The one identifiability threshold: the
        ``parameter_identifiable`` metric (and offline calibration) judge by it too.
    """

    period_s: float = setting(180.0, positive=True)
    threshold_k: float = setting(0.1, min=0.0)
    window_s: float = setting(10800.0, positive=True)
    min_window_s: float = setting(600.0, min=0.0)
    decimate: int = setting(20, min=1)
    max_iter: int = setting(3, min=1)
    coverage: float = setting(0.98, positive=True, max=1.0)
    weighting: str = setting("paper", choices=WEIGHTINGS)
    tau_s: float = setting(3600.0, positive=True)
    prior_weight: float = setting(1e-4, min=0.0)
    validate_s: float = setting(1800.0, positive=True)
    sensor_tolerance_k: float = setting(0.1, min=0.0)
    noise_k: float = setting(0.15, min=0.0)
    promote_z: float = setting(2.0, min=0.0)
    min_gain: float = setting(0.2, min=0.0)
    method: str = setting("sqp", choices=METHODS)
    params: tuple[str, ...] | None = None
    sensors: tuple[str, ...] | None = None
    max_rel_std: float = setting(0.5, min=0.0)
