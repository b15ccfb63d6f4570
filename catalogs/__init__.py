"""skyroute.catalogs: scenario and vehicle catalogs (YAML) and the small real data they need."""
