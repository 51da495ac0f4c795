"""``voxelwatch view``: the live web page of a home.

* :mod:`view.state`: what the view knows (pure: messages in, JSON-ready dicts out);
* :mod:`view.server`: the zenoh reader and the aiohttp server around it;
* :mod:`view.cli`: the command line and the process;
* ``static/``: the pages, their script and style (served from the package, nothing from elsewhere).

The plan geometry comes from :mod:`view.plan`.
"""
