"""Child process of :class:`harvest_qp.viewer.server.ViewerServer`: meshcat's web/zmq bridge.

Run as ``python -m harvest_qp.viewer._server_main --host H --port P --parent-pid PID``.
It differs from ``meshcat.servers.zmqserver`` in three ways (meshcat 0.3.2 pitfalls, see
STACK_NOTES):

* the web server binds ``--host`` only (meshcat binds every interface);
* a busy ``--port`` is an error (exit code 3, message on stderr), never a silent move to
  the next port; the zmq port is an ephemeral port on 127.0.0.1 chosen by the OS;
* a ``batch`` command applies many scene commands in one zmq round trip (meshcat's
  server answers each command separately: 0.1-0.3 ms each);
* a watchdog exits as soon as the parent process is gone (meshcat's child outlives a
  killed parent), and SIGINT is ignored so the parent decides when the server stops.

On success it prints ``zmq_url=...`` and ``web_url=...`` lines, like meshcat's server.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys

EXIT_PORT_BUSY = 3
EXIT_BAD_HOST = 4


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=7000)
    parser.add_argument("--parent-pid", type=int, default=0)
    args = parser.parse_args(argv)

    # Ctrl-C in a terminal reaches the whole process group: the parent handles it and
    # closes us; the watchdog covers a parent that dies without closing.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))

    import tornado.ioloop
    import zmq
    from meshcat.servers import zmqserver
    from meshcat.servers.tree import SceneTree, find_node

    class Bridge(zmqserver.ZMQWebSocketBridge):
        """meshcat's bridge without the port walk and with the web server bound to ``host``."""

        def __init__(self, host: str, port: int) -> None:  # noqa: D107 (no super(): it walks ports)
            self.host = host
            self.websocket_pool = set()
            self.app = self.make_app()
            self.ioloop = tornado.ioloop.IOLoop.current()
            socket = self.context.socket(zmq.REP)
            socket.bind("tcp://127.0.0.1:*")
            self.zmq_socket = socket
            self.zmq_stream = zmqserver.ZMQStream(socket)
            self.zmq_stream.on_recv(self.handle_zmq)
            self.zmq_url = socket.getsockopt_string(zmq.LAST_ENDPOINT)
            self.app.listen(port, address=host)
            self.fileserver_port = port
            url_host = f"[{host}]" if ":" in host else host
            self.web_url = f"http://{url_host}:{port}/static/"
            self.tree = SceneTree()

        def handle_zmq(self, frames):
            # b"batch" + (command, path, data) * n: one round trip for a whole viewer frame.
            if frames[0] == b"batch":
                body = frames[1:]
                if len(body) % 3:
                    self.zmq_socket.send(b"error: a batch needs (command, path, data) triples")
                    return
                for i in range(0, len(body), 3):
                    self.apply(body[i : i + 3])
                self.zmq_socket.send(b"ok")
                return
            super().handle_zmq(frames)

        def apply(self, frames):
            """meshcat's handling of one scene command, without the reply."""
            cmd = frames[0].decode("utf-8")
            path = [p for p in frames[1].decode("utf-8").split("/") if p]
            data = frames[2]
            node = find_node(self.tree, path)
            if not (cmd == "set_object" and node.object and node.object == data):
                self.forward_to_websockets(frames)
            if cmd == "set_transform":
                node.transform = data
            elif cmd == "set_object":
                node.object = data
                node.properties = []
            elif cmd == "set_property":
                node.properties.append(data)
            elif cmd == "set_animation":
                node.animation = data
            elif cmd == "delete":
                if path:
                    parent = find_node(self.tree, path[:-1])
                    if path[-1] in parent:
                        del parent[path[-1]]
                else:
                    self.tree = SceneTree()

    try:
        bridge = Bridge(args.host, args.port)
    except OSError as error:
        import errno

        if error.errno == errno.EADDRINUSE:
            print(f"port {args.port} on {args.host} is already in use: {error}", file=sys.stderr, flush=True)
            return EXIT_PORT_BUSY
        print(f"cannot listen on {args.host}:{args.port}: {error}", file=sys.stderr, flush=True)
        return EXIT_BAD_HOST

    parent = args.parent_pid

    def watchdog() -> None:
        # Re-parenting (to init or a subreaper) means the parent is gone.
        if parent and os.getppid() != parent:
            bridge.ioloop.stop()

    tornado.ioloop.PeriodicCallback(watchdog, 200).start()
    print(f"zmq_url={bridge.zmq_url}", flush=True)
    print(f"web_url={bridge.web_url}", flush=True)
    bridge.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
