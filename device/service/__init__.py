"""The probe service: HTTP/WebSocket API, dashboard, mDNS advertising and systemd integration.

``create_app`` (``lightprobe.device.service.app``) wires one :class:`aiohttp.web.Application`, with the
shared state in ``lightprobe.device.service.state`` and the routes in ``lightprobe.device.service.routes``; ``lightprobe
serve`` (``lightprobe.cli.serve``) runs it. Importing this package does nothing.
"""
