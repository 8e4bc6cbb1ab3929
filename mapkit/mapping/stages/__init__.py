"""The stages of ``mapkit build``, one module per stage folder of a session (``WORKSPACE/sessions/<name>/``).

- :mod:`.trajectory` (``trajectory/``): vehicle poses from the log
- :mod:`.georef` (``georef/``): GPS alignment into the workspace's ENU frame, with :mod:`.fusion` (the factor
  graph over odometry, GPS and the IMU, with loop closures) when ``georef.fuse`` asks for it
- :mod:`.map` (``map/``): the semi-dense map
- :mod:`.imagedb` (``imagedb/``): the georeferenced image database

Each stage is one function (``write_*``) or class that takes the session's folders, its section of the build
config and what it reads (the log, the session's sensor mounts, the upstream stages' outputs) as arguments,
writes its stage folder and returns it. Which stages run, in what order, whether a finished one is reused
(its ``.done`` marker), and the session's metrics and timings belong to the driver,
:class:`mapkit.mapping.build.SessionBuilder`. :mod:`.frames` holds the mapping camera and its posed frames
that stages 3 and 4 share, :mod:`.common` the units and plot axes that several stages state alike.
"""
