"""Tools that complete or create BOP datasets: ``cosy gt-info``, ``cosy new-dataset``."""
