"""The floor every stage stands on: errors, atomic file I/O, the camera and measurement model, the
clip folder's contract, frame reading, time offsets, input checks and process lifelines. Nothing
here imports from outside ``pipeline.core``; ``renderers``, ``detectors`` and
``pipeline.estimators`` import only from here (``tests/test_layers.py`` holds it)."""
