"""The benches (`clothball bench --load`, `--index`, `--empty-rooms`, `--soak`, `--admit`):
they drive a real server from outside, so none of the server's runtime modules imports
this package (an import-linter contract in pyproject.toml).

- ``loadbench``: rooms with real clients at real rates, step by step to the limit
  (``benchclients``: its load generator, a process of its own: clients set up in Python,
  then driven by a native pump, ``native/bench/load_clients.hpp``);
- ``indexbench``: the replay index's queries over many rounds;
- ``emptybench``, ``soakbench``, ``admitbench``: idle rooms' cost, hours of play, admission
  control, each against a ``clothball host`` of its own (``server.hostproc``).
"""
