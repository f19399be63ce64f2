"""wvr: the application layer. One command (``wvr``) over the packages' APIs, and the demo."""
