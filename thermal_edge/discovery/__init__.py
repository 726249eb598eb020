"""Model-gap discovery: find the physical effect a thermal model lacks, add it, show the gap shrink.

Adapting parameters cannot fix a model that lacks a physical effect: its errors then follow the
operating conditions in a way no parameter value removes. :func:`discover` takes a model file
(its raw YAML document) and a recorded run and

1. refits the model's adaptable parameters on the first 2/3 of the run (Gauss-Newton with the
   analytic sensitivities of :mod:`thermal_edge.estimation`), so that what remains is structural;
2. analyses the residuals per sensor against the operating variables (speed, current², the
   readings, the boundary temperatures, dT/dt, time) and by regime (:mod:`.residuals`);
3. lists every catalogue effect on every applicable target of the model (:mod:`.effects`) and
   scores each with the score test at zero effect (gradient and Gauss-Newton information of the
   prediction error with respect to the effect's parameters, the adaptable parameters projected
   out: ``g*ᵀ I*⁻¹ g*``), plus a screen against the residual at the nominal parameters;
4. fits the best few fully and ranks them on the held-out last third (RMS gap over the sensors,
   BIC penalty for the effect's parameters); the winner must lower the held-out gap by 10 % and
   0.05 K (``Options``);
5. adds the winner to the model (a few lines of YAML: :func:`.workflow.write_model` patches
   them into the original file), refits, and repeats until no candidate is accepted. With no
   winner in the first round the verdict is "no missing effect found";
6. judges the verdict (:mod:`.judge`): the runner-up's held-out gap against the winner's with
   its uncertainty (confusable effects are reported as a pair, with the evidence that separates
   them and the steady operating point that would; held-out data from an operating region the
   training part lacks decides where the run has one), and the gap against the sensor noise
   floor ("no gap" against "a gap the catalogue does not explain": its size, where and when,
   the nearest candidates). :mod:`.report` writes a Markdown report with PNG figures
   (matplotlib, the ``report`` extra).

Effects (``NAME[:TARGET][=PARAM=VALUE,...]``, the syntax of ``thermal-edge simulate --effect``;
``s = |speed| / n_ref``, ``n_ref``/``i_ref`` the run's 95th-percentile speed/current):

=====================================  =========================================================
``copper_temperature``                 winding loss ``X + (k100-1)(T-t_ref)/100 X(t_ref)``
``speed_convection:<group>``           conductance ``g (1 + k s^m)``
``iron_loss_frequency``                iron loss ``X (1 + k s^m)``
``magnet_eddy_loss``                   magnet loss ``p (s i/i_ref)²``
``bearing_loss``                       shaft/end-cap loss ``p s``
``housing_radiation``                  frame heat out ``eps_a σ (T⁴ − T_amb⁴)``
``natural_convection``                 frame heat out ``h max(T − T_amb, 0)^1.25``
``sensor_lag:<sensor>``                probe node, time constant ``tau`` s
``ambient_offset[:<boundary>]``        air ``dT`` K warmer than the boundary input
``contact_resistance:<conductance>``   extra series ``R`` K/W
=====================================  =========================================================

Parameters, defaults and bounds: :data:`.effects.CATALOGUE` (its table is in the docstring of
:mod:`.effects`; ``thermal-edge discover --model M --list-effects`` prints it).
Unset magnitudes of a hidden effect are raised (doubled, up to 8 times) until the plant differs
from the model by at least 1 K RMS on some sensor over the cycle. Targets: a conductance group
is named by the parameters its law uses (``R_e_hous``, ``h_gap0+h_gap1``) or by its two ends
(``st-pm``); a single conductance by its ends (``housing_6-yoke_1``); ``thermal-edge discover
--model M --list-effects`` lists them. Node roles (winding, stator iron, magnet, shaft/end cap,
frame) are read from the model file's ``role:`` of each node.

Command line: ``thermal-edge discover --model M --run R [--format F] [--sensors a,b] [--out DIR]
[--json]``; benchmark (from the checkout): ``make bench-discovery``.
"""
from .effects import CATALOGUE, Candidate, Effect, EffectError, parse_spec
from .workflow import Discovery, Options, discover, write_model

__all__ = ["CATALOGUE", "Candidate", "Discovery", "Effect", "EffectError", "Options", "discover", "parse_spec", "write_model"]
