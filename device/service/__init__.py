"""The probe service: HTTP/WebSocket API, dashboard, mDNS advertising and systemd integration.

``create_app`` (``device.service.app``) wires one :class:`aiohttp.web.Application`, with the
shared state in ``device.service.state`` and the routes in ``device.service.routes``; ``lightprobe
serve`` (``device.cli.serve``) runs it. Importing this package does nothing.
"""
