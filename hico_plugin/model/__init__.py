"""The HiCo model: owns field, renderer and losses; decides what each step renders."""
