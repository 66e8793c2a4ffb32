#ifndef EMBEDRL_FAKE_PLATFORM_H
#define EMBEDRL_FAKE_PLATFORM_H

#include <stdbool.h>

#include "platform.h"

#define FAKE_MAX_SENT 256u

void fake_reset(void);
unsigned fake_sent_count(void);
const can_frame_t *fake_sent(unsigned index);
void fake_set_ms(uint32_t ms);
/* Make transport_send fail (as on bus-off or a link down) until called with false. */
void fake_fail_sends(bool fail);

#endif
