"""The application: one clip through every stage (``run``), folders of clips (``batch``), their
manifests, and the ``stereotrack`` command line on top."""
