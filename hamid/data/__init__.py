"""Recordings in and outputs out: tables of every format (text, Parquet, lab files),
column roles and units, records grouped by trajectory, loading whole or in chunks,
noise levels and derived velocities, and writing files safely."""
