"""One workflow function per command: the computation of the lower layers, then the
outputs (files, figures, reports) of :mod:`jaxlift.report`.

The command line (:mod:`jaxlift.cli`) only parses arguments and calls these; a notebook
can call them directly.
"""
