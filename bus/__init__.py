"""skyloop's bus package: the wire (see DESIGN.md). Imports nothing internal.

- :mod:`bus.keys`: key expressions ``skyloop/<vehicle>/<topic>`` and the topic table.
- :mod:`bus.messages`: the rosbags type store (ROS 2 Humble + ``skyloop_msgs`` from
  ``bus/msg/*.msg``), the CDR codec, message constructors and extractors.
- :mod:`bus.session`: session configuration, hub discovery, the Python router.
- :mod:`bus.node`: :class:`bus.node.Bus` (typed publishers/subscribers on a session).
- :mod:`bus.log.writer`: the MCAP episode log writer; :mod:`bus.log.reader`: the reader.
- :mod:`bus.log.record`: the recorder (``skyloop record``).
"""
