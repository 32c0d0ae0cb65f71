import json, sys, numpy as np, gymnasium as gym, c3bf_gym
from c3bf_gym.filter import scenario_envelope
from c3bf_gym.safety import FilterConfig
env = gym.make(sys.argv[1]).unwrapped
env.reset(seed=0)
e = scenario_envelope(env, FilterConfig())
v = np.linspace(0.0, 0.5, 101)
d = [e.min_sensing_range(x) for x in v]
d = [min(x, 5.0) for x in d]
json.dump([v.tolist(), d], open(sys.argv[2], "w"))
print(e.max_speed, d[::10])
