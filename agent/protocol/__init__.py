"""What crosses a process boundary: the key space and every message of uma's protocols.

One module per protocol; each builds and checks its own messages and says in its
docstring who sends what to whom.  Nothing here opens a session or keeps state.
"""
