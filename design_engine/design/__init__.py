"""Design: tasks (data in `tasks/`), objectives, constraints, the evaluator, MMA and the
optimiser driver, design files, run outputs, export and design plots."""
