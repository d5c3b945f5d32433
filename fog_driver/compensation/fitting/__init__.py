"""Fitting the drift models: the fit data, structure and model choice, the ridge solver, the quality checks."""
