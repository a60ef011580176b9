"""The probe service: HTTP/WebSocket API, dashboard, mDNS advertising and systemd integration.

``create_app`` (``device.service.app``) wires one :class:`aiohttp.web.Application`; ``lightprobe
serve`` (``device.service.cli``) runs it. Importing this package does nothing.
"""
