"""The headline experiment (issue #7): policy training on the simulated rover and the
static / heuristic / RL comparison over the six scenarios of the ReSPEC paper.

* ``frames``   what the sensors deliver at one scene instant for one configuration
* ``cache``    the detector's outcome per (scene frame, sensor configuration), on disk
* ``rollout``  a controller driven through scenario segments on cached outcomes
* ``training`` ``respecd train-policy``: randomized episodes, learning curve, saved table
* ``compare``  ``respecd bench scenarios``: the three policies, metrics and summary
* ``report``   the Markdown table and the figure
* ``logbench`` the same comparison replayed counterfactually on a recorded session
"""
