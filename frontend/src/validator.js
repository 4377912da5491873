/** glTF validation in the browser with the Khronos validator (npm gltf-validator), loaded on first use. */

/**
 * Validate GLB or glTF bytes. External resources are not fetched (reported as unresolved by the validator).
 * @param {ArrayBuffer} buffer
 * @param {string} name file name, for the report
 * @returns {Promise<{numErrors: number, numWarnings: number, numInfos: number, numHints: number,
 *   messages: {code: string, message: string, severity: number, pointer?: string, offset?: number}[],
 *   truncated: boolean, info: any, validatorVersion: string}>}
 */
export async function validateGltf(buffer, name = 'model.glb') {
  const { validateBytes, version } = await import('gltf-validator');
  const report = await validateBytes(new Uint8Array(buffer), {
    uri: name,
    maxIssues: 200,
    externalResourceFunction: (uri) => Promise.reject(new Error(`external resource ${uri} is not loaded`)),
  });
  return {
    ...report.issues,
    info: report.info,
    validatorVersion: version(),
  };
}

export const SEVERITY = ['error', 'warning', 'info', 'hint'];
