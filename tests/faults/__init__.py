"""The fault corpus: bad inputs and hostile SQL against onboard, query, sql and compact (see cases.py)."""
