"""Reference ropes: the file format, event detection, fine simulators and hand paths."""
