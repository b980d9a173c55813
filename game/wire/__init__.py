"""The neutral ground of the server and every client: the protocol codec (``protocol``) and
the replay file format (``replay``). Imports nothing else of the package."""
