"""The app's routes, one router per concern: :mod:`.health` (``/healthz``, ``/readyz``), :mod:`.metadata`
(``/v1/metadata``), :mod:`.metrics` (``/metrics``), :mod:`.occupancy` (``POST /v1/occupancy``), :mod:`.ui` (the
browser page ``/ui``, unless ``OCCFLOWNET_UI=0``)."""
