"""Many recordings: one fit per file (many_files) and the records of `fit --each`
written as they come (each_output)."""
