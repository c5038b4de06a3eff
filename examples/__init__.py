"""Worked examples: a TorchRL collector on the fused reward, and scripted reference policies of classic
control tasks for ``trainer.reference=`` (``examples.cartpole``, ``examples.mountain_car``)."""
