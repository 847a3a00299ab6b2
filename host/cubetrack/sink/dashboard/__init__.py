"""The web dashboard (docs/dashboard.md): one page served over HTTP, updated by server-sent events.

- :mod:`~cubetrack.sink.dashboard.state`: what the page shows, as one thread-safe model with a
  JSON form for every part (camera tiles, top view, robots, panels of the workflow);
- :mod:`~cubetrack.sink.dashboard.draw`: camera frames annotated with OpenCV, the top view's geometry;
- :mod:`~cubetrack.sink.dashboard.server`: the HTTP server, its JSON endpoints and event stream,
  and :class:`~cubetrack.sink.dashboard.server.DashboardSink`, the sink a session feeds.

The page itself (``static/``) is plain HTML, CSS and JavaScript: no build step, nothing fetched
from elsewhere.
"""
