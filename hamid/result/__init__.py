"""The fit's result: the report's parts and warnings (summary), `FitResult` and its
JSON (fit_result), checked against the schema when read back (validation)."""
