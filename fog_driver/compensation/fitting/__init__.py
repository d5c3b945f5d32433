"""Fitting the drift models: the fit data (``data``), the ridge solver (``ridge``), each kind's fit and its
structure choice (``wesn``, ``svr``, ``fit``), the report and the quality checks (``report``, ``quality``)."""
