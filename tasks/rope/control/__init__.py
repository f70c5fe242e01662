"""Steering real throws: the command space, planning on the coarse model, correction over trials, sensitivity."""
