"""The server's service layer: what the routers, the worker and the CLI call.

One module per concern: ``accounts``, ``challenges``, ``uploads`` (sessions) and
``upload_files`` (their bytes on disk), ``submissions``, ``methods`` (method cards),
``scores`` (what is stored of a result), ``queue`` and ``leaderboard``. The routers in
:mod:`semantic3d.server.routers` parse requests and call these, never the other way round;
the worker and the ``admin`` commands call them too.
"""
