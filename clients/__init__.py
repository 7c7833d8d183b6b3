"""Clients of the fingertrack service: the Python client library, the glove simulator, the demo, the
Unity C# client and the web viewer (the load tests live in ``service/bench/load.py``)."""
