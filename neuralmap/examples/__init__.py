"""Worked examples that run end to end on the package (each also runs in the test suite at
a tiny size).

- `neuralmap.examples.gnss_outage`: a GNSS/INS solution whose GNSS drops out hands
  over to terrain-aided navigation (``neuralmap-gins`` then ``neuralmap-navigate``).
"""
