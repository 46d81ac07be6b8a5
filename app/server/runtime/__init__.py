"""What runs inside the console: the source, the fusion pipeline, the stream, background watchers,
``trifuse serve``.
"""
