"""The desktop client: a pyglet window that renders what the server (or a replay) says.

Pure logic lives in modules that need no window and are tested without one:
``interp`` (frame assembly and interpolation), ``model`` (room, scores, events, connection
state from the server's JSON messages), ``lobby_ui`` (the lobby screens' state and hit
tests), ``replay`` (replay files and a seekable player) and ``netthread`` (the websocket
client on its own thread with a latest-wins handover). ``render`` and ``app`` need a GL
context; they only draw the state the others compute.
"""
