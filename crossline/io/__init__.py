"""Input and output at the edges: capture folders, images, atomic artefact writes, provenance.

Module map: ``capture`` (read and validate a capture folder, DESIGN.md §2), with its parts
``contract`` (the capture's constants, ``Problem``, ``CaptureError``, files kept inside the
capture), ``rig`` (rig.yaml) and ``tables`` (frames.csv and poses.csv rows), which ``capture``
re-exports; ``images`` (read and write the capture's images, errors that name the file),
``atomic`` (every artefact written to a temporary file and renamed into place), ``provenance``
(the source files a stage depends on, checksums, version and commit), ``columns`` (a stage
table's parquet columns as arrays, row group by row group: no DataFrame of a long scan).
"""
