"""`hamid select`: the candidate terms of a library (library), the best-subset
search (best_subsets), the selection and its refit (select_terms) and its
report (select_render)."""
