"""Task plugins of the harness, and their gymnasium registrations.

Importing :mod:`tasks` registers the environments below (cheap: no simulator is imported until
``gymnasium.make`` is called). One ``register`` call per task; keep this file a plain list.
"""

import gymnasium

gymnasium.register(id="harness/CartPoleSwingUp-v0", entry_point="tasks.cartpole:make_gym_env")
gymnasium.register(id="harness/CartDoublePendulumSwingUp-v0", entry_point="tasks.double_pendulum:make_gym_env")
gymnasium.register(id="harness/Unicycle-v0", entry_point="tasks.unicycle:make_gym_env")
gymnasium.register(id="harness/DMCCartpoleSwingup-v0", entry_point="tasks.dmc_cartpole:make_gym_env")
