"""Development tools: ``trifuse bench`` (benchmarks, the stream soak) and the console subprocess
they drive.
"""
