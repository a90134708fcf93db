"""Learners: MADDPG (centralised critics) and DDPG (local critics) sharing one update."""
