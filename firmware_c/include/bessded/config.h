/*
 * Host-side provisioning: an agent's TOML configuration file (docs/firmware-spec.md
 * section 3, the same file `bess-ded agent --config` reads) and its key file (section
 * 12, written by `bess-ded keys`) into the integers the runtime uses. This is the one
 * place binary64 arithmetic happens (q24, q30, rne of the spec's formulas), exactly as
 * the spec writes it; the runtime and the core never see a floating-point value. An MCU
 * port runs it on the host and flashes the resulting bd_agent_params.
 */
#ifndef BESSDED_CONFIG_H
#define BESSDED_CONFIG_H

#include <stddef.h>

#include "bessded/agent.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Parse and check an agent configuration (CFG-1..7). text: the TOML; src: its name in
 * messages. On error returns nonzero and writes "SRC: [key] expected ..., but got ..."
 * (firmware_py's ConfigError wording) into err. */
int bd_config_parse(const char *text, const char *src, bd_agent_params *p, char *err,
                    size_t errlen);

/* bd_config_parse of a file's contents. */
int bd_config_load(const char *path, bd_agent_params *p, char *err, size_t errlen);

/* Load a node key file (owner-only 0600, format bess-ded-secoc-node-key/1) for node
 * label `node`; sets k->persist_boot to rewrite the file's boot counter. */
int bd_keyfile_load(const char *path, const char *node, bd_keyring *k, char *err,
                    size_t errlen);

/* The public --insecure keyring of `node` (AUTH-20). */
int bd_keyring_insecure(const char *node, bd_keyring *k);

#ifdef __cplusplus
}
#endif

#endif /* BESSDED_CONFIG_H */
