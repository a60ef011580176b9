"""HTTP routes of the service, one module per resource; each has ``add_routes(app, ...)``.

- :mod:`.probe`: ``/api/v1`` status, health, lights, maps, previews, config, the stream, the
  dashboard's static files;
- :mod:`.q2tree`: ``/api/v1/q2tree`` (the binary tree for host-side merging);
- :mod:`.calibration`: ``/api/v1/calibration`` and the technician's ``/calibrate`` page.

Handlers read the shared state through :data:`lightprobe.device.service.state.STATE`.
"""
