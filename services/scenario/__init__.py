"""Navigation scenarios in the simulator, judged on its ground truth: the file model, the client view of a running
stack, the single-robot runner with its mapping phase, several robots, VDA 5050 orders, generated goals, the
robustness suite and the reports."""
