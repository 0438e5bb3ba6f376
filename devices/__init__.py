"""Camera and bench hardware behind interfaces, each with a simulated twin that runs the real protocol code."""
