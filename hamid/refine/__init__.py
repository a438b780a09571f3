"""The trajectory refinement: the linear fit's parameters refined by fitting the
integrated model to the samples (joint_refinement, trajectory, integration, dop853;
outcome: what it hands back). Knows nothing of reports, figures, selection, batches or
the CLI."""
