"""The generated reference pages of the manual, one module per table (``deploy/gen_docs.py`` is the
command that renders them; the docs build writes them to ``docs/_generated/``).

- :mod:`.can` -- the CAN interface, from ``dbc/thermal_edge.dbc`` (cantools);
- :mod:`.config` -- every key of ``config/edge.yaml``: shipped value, the default declared in the
  dataclasses of ``thermal_edge.config`` (read as data), unit and the file's own comment;
- :mod:`.metrics` -- every metric family of the running service (``/metrics`` HELP and TYPE lines;
  label names from the samples and from ``thermal_edge.service.metrics.LABELS``);
- :mod:`.alerts` -- the Prometheus alert rules;
- :mod:`.cli` -- every command's ``--help``, from the command-line parser;
- :mod:`.sim_config` -- ``deploy/compose/edge-sim.yaml``, the compose demo's service configuration.

Each module renders from its source alone; :mod:`.markdown` holds the table cells they share, :mod:`.paths` the files they read.
"""
