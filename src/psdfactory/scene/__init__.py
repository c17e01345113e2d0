"""Making scenes: sample → simulate → render → label, one scene folder at a time.

No torch here (a scene job starts in well under a second). ``stages`` runs the stages as
file-to-file steps; the other modules are the pure functions they call.
"""
