"""Small pretrained checkpoints shipped inside the package (``weights/<bundle>/``), the commands that
make and list them, and the ``pretrained`` stage that shows them working on a run's held-out data.

A 2-core CPU cannot train a tokenizer and a generator to a useful quality within the demo's
minutes, so the demo trains every stage briefly (every code path runs) and, next to that, shows
what the same pipeline does after a longer training: these bundled checkpoints, labelled as such.
"""
