"""The asyncio websocket client (``client``) and the connection it and the server use
(``tap``: binary messages in and out without websockets' per-message work)."""
