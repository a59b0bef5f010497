"""The evolution MDP behind other libraries' interfaces: Gymnasium and Stable-Baselines3.
"""
