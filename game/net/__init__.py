"""The asyncio websocket client (``client``) and the websockets fast paths (``fastpath``)."""
