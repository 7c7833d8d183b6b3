"""The service's listening socket (``api.server.listen_socket``, what ``fingertrack serve`` listens on):
the connections it accepts under asyncio (as uvicorn serves them) have Nagle's algorithm off, as the
clients' connections have. With it on, a frame written while the previous one waited for its
acknowledgement waited for the peer's delayed acknowledgement (about 40 ms; ``bench latency``'s tail)."""
import asyncio
import socket

from service.api.server import free_port, listen_socket


def _nodelay(sock: socket.socket) -> bool:
    return bool(sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY))


def test_accepted_connections_have_nagle_s_algorithm_off():
    async def main() -> tuple[bool, bool]:
        port = free_port()
        accepted: asyncio.Future = asyncio.get_running_loop().create_future()

        async def handle(reader, writer):
            accepted.set_result(_nodelay(writer.get_extra_info("socket")))
            writer.close()

        server = await asyncio.start_server(handle, sock=listen_socket("127.0.0.1", port))
        try:
            _, writer = await asyncio.open_connection("127.0.0.1", port)
            client = _nodelay(writer.get_extra_info("socket"))
            served = await asyncio.wait_for(accepted, 30.0)
            writer.close()
        finally:
            server.close()
            await server.wait_closed()
        return served, client

    served, client = asyncio.run(main())
    assert client, "the client side (asyncio's own connection) is the reference"
    assert served


def test_the_websocket_protocol_pauses_reading_only_once_its_queue_holds_queue_high_messages():
    """``DrainingWebSocket``: uvicorn paused reading after every received message and resumed it when the
    app took it (two changes of the loop's selector per message); here reading pauses once ``QUEUE_HIGH``
    messages wait for the app, and resumes once it has taken them all."""
    from types import SimpleNamespace

    from service.api.server import DrainingWebSocket

    async def main():
        calls = []
        proto = DrainingWebSocket.__new__(DrainingWebSocket)
        proto.queue, proto.read_paused, proto.close_sent = asyncio.Queue(), False, False
        proto.transport = SimpleNamespace(pause_reading=lambda: calls.append("pause"),
                                          resume_reading=lambda: calls.append("resume"))
        seen = []
        for k in range(DrainingWebSocket.QUEUE_HIGH + 3):
            proto.curr_msg_data_type, proto.frames = "text", [str(k).encode()]
            proto.send_receive_event_to_app()
            seen.append(list(calls))
        got = [(await proto.receive())["text"] for _ in range(DrainingWebSocket.QUEUE_HIGH + 3)]
        return seen, calls, got, proto.read_paused
    seen, calls, got, paused = asyncio.run(main())
    high = DrainingWebSocket.QUEUE_HIGH
    assert seen[high - 2] == [] and seen[high - 1] == ["pause"] and seen[-1] == ["pause"]
    assert calls == ["pause", "resume"] and not paused
    assert got == [str(k) for k in range(high + 3)]
