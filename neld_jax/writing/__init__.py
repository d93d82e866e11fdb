"""Writing what a run made: its outputs and metrics.json (`outputs`), the output folder and what a rerun does
(`output_folder`), poses and maps in the field's formats (`export`), the evaluation against ground truth with its
files and figures (`evaluate`, `plots`), the Rerun recording (`viewer`) and each recording's outputs in a run over
several (`session_outputs`)."""
