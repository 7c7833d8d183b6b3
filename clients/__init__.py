"""Clients of the fingertrack service: Python client, glove simulator, load tests."""
