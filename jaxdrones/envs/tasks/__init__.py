"""The paper's tasks on the composable env layer (`jaxdrones.envs.core`): single-agent (`single`) and
multi-agent (`multi`)."""
