"""Storage: the recorded rounds and their index.

- ``recorder``: a round's recording, spooled to disk while it is played;
- ``index``: the replay index's interface (``ReplayIndex``), its retention and keys;
- ``sql``: the SQL both drivers run (``SqlIndex``);
- ``sqlite``, ``postgres``: the drivers (the data directory's own index, a cluster's shared
  one);
- ``datadir``: the data directory as the server uses it (``Storage``: recording on or off,
  and why).
"""
