"""Control: state, reward, tabular Q-learning, baselines, and applying actions."""
