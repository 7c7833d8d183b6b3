"""Scale-out on NATS: stateless gateways and hand workers in their own processes.

``fingertrack worker --bus nats://HOST:PORT`` runs hand workers that own sessions;
``fingertrack serve --bus nats://HOST:PORT`` runs a gateway (the same WebSocket and REST API) that
forwards each session's source messages to its owning worker and fans that session's frames and
gesture events out to its own subscribers. The subjects, messages and the ownership lease are in
``subjects.py``; the worker in ``worker.py``; the gateway's session proxy in ``gateway.py``.
Needs the optional extra ``nats`` (``nats-py``); without ``--bus`` nothing here is imported.
"""
