"""All plotting and report writing: the report document (Markdown + HTML), plots of
logs and analyses, and the fit, posterior and tuning reports.

Computation never imports this layer; plotting never changes matplotlib's backend
(figures are plain :class:`matplotlib.figure.Figure` objects, see :mod:`jaxlift.report.figures`).
"""
