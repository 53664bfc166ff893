"""The paper's tasks on the composable env layer (`jaxdrones.envs.config`, `jaxdrones.envs.task`,
`jaxdrones.envs.env`): single-agent (`single`, `gate`, `avoid`) and multi-agent (`multi`)."""
