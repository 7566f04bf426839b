"""Sub-commands of the ``ctrplan`` command line (one module each, see :mod:`ctrplan.cli`)."""
