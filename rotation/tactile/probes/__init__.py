"""`rotate probe`: frozen touch features against end-to-end training at label budgets (data, skin decoders,
report, the job)."""
