"""Whole keepaway cycles in compiled code (numba), per field: decisions, the keepers' and takers'
skills, physics, referee, the players' world models, state variables, the benchmark keepers and
the SMDP advance to each field's next decision (``KeepawayConfig.kernels="cycle"``).

One module per torch module it mirrors, in the same order of operations but in float64 scalars:
physics.py, skills.py, keepers.py, takers.py, referee.py, perception.py, state_vars.py,
policies.py, and cycle.py for simulator.py's cycle; common.py holds what they share (the compile
options, the parameter indices, the state as one :class:`CycleState`), kernels.py the entry
points and glue.py the :class:`CompiledCycle` a simulator drives them with. The constants of the
skills, the world models, the referee and the benchmark keepers are imported from the torch
modules that name them (numba freezes them when it compiles). The state is stored as float32
after every cycle, so one cycle agrees with the torch path within float32 rounding (not bit for
bit: transcendental functions and the intermediate precision differ; a branch taken on a near-tie
can differ).

Randomness: ``kernels.cycle`` reads the uniforms the torch path draws (``u`` [B, U], in its order), so
a single cycle can be compared with torch's; the multi-cycle kernels (``advance_fields``,
``advance_any``, ``play``) draw from one splitmix64 generator per field (``rng`` [B]), so a field's
play does not depend on the batch size, the thread count or the other fields.
"""

from hfrl_torch.envs.keepaway.compiled.common import CycleState
from hfrl_torch.envs.keepaway.compiled.glue import Advance, CompiledCycle

__all__ = ["Advance", "CompiledCycle", "CycleState"]
