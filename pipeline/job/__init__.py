"""Layer 11, above ``stages/``: the job description and its YAML loading, the context a job carries
from stage to stage, the runner, executors and batches, output folders and the terminal display."""
