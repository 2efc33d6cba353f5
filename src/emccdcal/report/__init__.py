"""What people look at: :mod:`~emccdcal.report.figures` (the paper's figures),
:mod:`~emccdcal.report.html` (the self-contained HTML report) and
:mod:`~emccdcal.report.corner` (corner plots of posterior samples)."""
