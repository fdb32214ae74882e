"""hmi_api: the HTTP + WebSocket API, the web HMI (``static/``) and the SQLite pose database (see README.md).

Core modules are I/O-free (``posedb``, ``jog``, ``view``, ``auth``); ``backend`` links them to Zenoh, ``app`` is the
Litestar application and ``node`` runs it under uvicorn on the service's event loop.
"""
