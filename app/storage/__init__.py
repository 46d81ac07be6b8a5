"""What trifuse keeps on disk: capture directories, rig files, previews, atomic writes, the work-
directory lock.
"""
