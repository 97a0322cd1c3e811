"""``respecd fleet``: evaluate, learn and sweep over many robots' logs — in this process, in a
pool of processes, or on Ray — with the same answer from every backend, in any input order."""
