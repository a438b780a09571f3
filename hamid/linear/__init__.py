"""The linear fit: which rows (plan), the row blocks (design, quadrature), least
squares (solve), the covariance estimators (uncertainty), the fit in memory
(estimate) and in chunks (chunked), adjusted least squares (adjust).

Knows nothing of reports, figures, selection, batches or the command line."""
