"""What a researcher reads after runs: one table over many run dirs and a page per run (a library;
the command lines are :mod:`tivne.collect` and :mod:`tivne.report`).

* :mod:`~tivne.reporting.runs`: run dirs -> :class:`RunRow` (overrides, metrics, status) -> one
  :class:`ResultsTable`, written as Markdown, CSV or JSON.
* :mod:`~tivne.reporting.events`: scalar curves from a run's TensorBoard events.
* :mod:`~tivne.reporting.raster`: a CPU z-buffer rasteriser for mesh snapshots (no display, no OpenGL).
* :mod:`~tivne.reporting.figures`: the report's matplotlib figures (Agg backend).
* :mod:`~tivne.reporting.page`: :func:`write_report`, the page and its PNGs in the run dir.
"""
