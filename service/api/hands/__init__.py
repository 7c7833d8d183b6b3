"""Hand workers of the embedded service: every session's hand runs in a worker process, the web
process only moves messages (``pool``: the web side, ``worker``: the process, ``owner``: what a
process owning a session keeps, shared with the NATS bus workers)."""
