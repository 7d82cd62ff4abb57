"""The browser workbench (``workbench serve``): a viser server over one estimation run, with the estimator in a
background process. Start it with :func:`workbench.app.ui.server.serve`."""
