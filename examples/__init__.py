"""Worked examples: a TorchRL collector on the fused reward, scripted reference policies of classic control
tasks for ``trainer.reference=`` (``examples.cartpole``, ``examples.mountain_car``), and a task of one's own
with its reference (``examples.catch``, docs/tutorial.md)."""
