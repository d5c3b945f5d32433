"""The lab's controllers, chosen by URL (``registry.open_controller``): thermal chambers now, a turntable to
come.  ``base`` is the interface, ``url`` the URL's shape, ``codecs`` the protocols' bytes (sans-IO), ``links``
the sockets and serial lines, and one driver module per controller family."""
