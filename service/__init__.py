"""fingertrack service: hand model, simulator, estimators, pipeline and API."""
