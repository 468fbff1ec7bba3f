"""Scenario-quality evaluation: fidelity, exploitability (CCE-gap), diversity, risk, export, report.

    rollouts.py        record_episodes / logged_episodes -> Trajectories (host arrays every metric reads)
    fidelity.py        histograms, Hellinger / KL / W1, realism score (ours, Sim-Agents style)
    exploitability.py  best responses against a frozen profile, CCE-gap with a CI over seeds
    diversity.py       mean pairwise displacement of a scene's episodes
    risk.py            collisions, min TTC, min gap, hard braking, ranking of critical scenarios
    export.py          scenes and generated episodes to GPUDrive processed JSON
    report.py          `tg-gpudrive report` (report_main, main)
"""
