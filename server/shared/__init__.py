"""What a host's processes share (``docs/architecture.md``): the line a gateway puts
before each connection it hands to the engine (``proxyline``) and the tie that ends a
child process with the host that started it (``lifeline``). The engine side and the
gateway side both import this package, and it imports nothing else of the server."""
