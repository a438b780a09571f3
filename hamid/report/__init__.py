"""Results rendered: a table, markdown, CSV, JSON, a summary or HTML (formats), and
several fits side by side (comparison). Reads results; never fits."""
