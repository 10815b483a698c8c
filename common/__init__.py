"""Small helpers with no product knowledge, below every other package (numpy, OpenCV and the
standard library only): atomic file writes, the Bayer mosaic, the root of every package's errors."""
