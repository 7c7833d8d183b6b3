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
